"""The mismatch radius: a proved bound of the real loop's deviation from the nominal one under an
input-scale range, and the radius it certifies (issue 54, item 3, continuous loop).

Oracles: the (2,0) law at e = 0 along a circle written here (its output jet, its command and the
plant with scaled, clipped inputs), SciPy's ``expm`` and DOP853 integrations of that plant at the
corners of the scale range and inside it, from initial errors on the proved sphere.
"""

from __future__ import annotations

import jax
import jax.numpy as jnp
import numpy as np
import pytest
import scipy.integrate
import scipy.linalg

import wmrjax.certify as C
from tests.test_certify_real_loop import EPS, OMEGA, T_FINAL, _problem, _reference_jet
from wmrjax.certify import affine
from wmrjax.problem import Problem

LIMIT = np.array([1.3, 0.8])
SCALES = (0.98, 1.02)  # every actuator within +-2 % of the law's
# the circle law's error matrix, written out: poles -1, -1 per coordinate, rows (x, y, vx, vy)
A = np.array([[0, 0, 1, 0], [0, 0, 0, 1], [-1, 0, -2, 0], [0, -1, 0, -2]], float)


def _loop(scale, limit):
    """The (2,0) law at e = 0 around a plant that applies clip(scale * (chi1, theta')): state
    (x, y, theta, chi1); chi1 (the compensator) integrates the law's own command."""

    def field(t, z):
        x, y, th, chi = z
        s, c = np.sin(th), np.cos(th)
        ref = _reference_jet(t)
        v = -(OMEGA**2) * ref[:2] - 2.0 * (chi * np.array([-s, c]) - ref[2:]) - (np.array([x, y]) - ref[:2])
        eta = np.clip(np.asarray(scale) * np.array([chi, -(c * v[0] + s * v[1]) / chi]), -limit, limit)
        return [-eta[0] * s, eta[0] * c, eta[1], -s * v[0] + c * v[1]]

    return field


def _zeta(z):
    """Output jet (x, y, x', y') of states (..., 4): the law's velocity output is chi1 (-sin, cos)."""
    x, y, th, chi = np.moveaxis(np.asarray(z), -1, 0)
    return np.stack([x, y, -chi * np.sin(th), chi * np.cos(th)], axis=-1)


def _state(e0):
    p0 = _reference_jet(0.0) + e0
    return [p0[0], p0[1], np.arctan2(-p0[2], p0[3]), np.linalg.norm(p0[2:])]


@pytest.fixture(scope="module")
def certified():
    """The problem certificate of the circle loop with limits and a +-2 % input-scale range."""
    plant = {"input_limit": LIMIT.tolist(), "input_scale": [[SCALES[0]] * 2, [SCALES[1]] * 2]}
    setting = _problem(plant).setting("certification")
    params = setting.params()
    exact = {
        b: C.exact_map_radius(setting.ctrl, params, t_final=T_FINAL, eps=EPS, basis=b, n_t=601)
        for b in ("full", "position")
    }
    return setting, params, C.problem_certificate(setting, params, exact, eps=EPS, n_directions=8)


def test_the_deviation_rate_is_the_closed_form_of_the_scaled_plant():
    setting = _problem({"input_scale": [[0.9, 1.1], [1.0, 1.0]]}).setting("c")
    params = setting.params()
    ctrl = setting.ctrl
    assert np.allclose(np.asarray(ctrl.error_matrix(params.gains)), A)
    rng = np.random.default_rng(0)
    for t in rng.uniform(0.0, T_FINAL, 5):
        err, scale = 0.2 * rng.normal(size=4), rng.uniform(0.9, 1.1, 2)
        jet = ctrl.reference_jet(t, params)[:3]
        delta, applied = (np.asarray(x) for x in C.deviation_rate(ctrl, params, jet, jnp.asarray(err), scale, 1.0))
        # closed form: zeta' = (eta1 (-s, c), eta1' (-s, c) + eta1 theta' (-c, -s)); the scaled
        # plant changes eta1 in the first row and theta' in the second
        x, y, th, chi = _state_at(t, err)
        nominal = np.array(_loop(np.ones(2), np.full(2, np.inf))(t, [x, y, th, chi]))
        eta2 = nominal[2]
        s, c = np.sin(th), np.cos(th)
        want = np.concatenate(
            [(scale[0] - 1) * chi * np.array([-s, c]), (scale[1] - 1) * eta2 * chi * np.array([-c, -s])]
        )
        assert delta == pytest.approx(want, abs=1e-12)
        assert applied == pytest.approx(scale * np.array([chi, eta2]), abs=1e-12)


def _state_at(t, err):
    """The state whose output jet is the reference's at t plus ``err``."""
    p = _reference_jet(t) + err
    return p[0], p[1], np.arctan2(-p[2], p[3]), np.linalg.norm(p[2:])


def test_the_deviation_bound_holds_on_simulated_runs_and_the_radius_keeps_eps(certified):
    setting, params, pc = certified
    ts = np.linspace(0.0, T_FINAL, 3001)
    E = np.stack([scipy.linalg.expm(A * t) for t in ts])
    rng = np.random.default_rng(4)
    for basis in ("full", "position"):
        b = pc[basis]
        mm = b["mismatch"]
        assert b["kind"] == "proved" and b["covers"] == ["nominal", "input_limit", "input_scale"]
        assert 0.0 < b["radius"] <= b["falsified_radius"]
        P = np.asarray(C.slice_basis(setting.ctrl, basis))
        dirs = rng.normal(size=(6, P.shape[1])) @ P.T
        dirs /= np.linalg.norm(dirs, axis=1, keepdims=True)
        worst_dev, least = 0.0, np.inf
        for k, d in enumerate(dirs):
            scale = [SCALES[k % 2], SCALES[(k // 2) % 2]] if k < 4 else rng.uniform(*SCALES, 2)
            e0 = 0.999 * b["radius"] * d
            sol = scipy.integrate.solve_ivp(
                _loop(scale, LIMIT), (0.0, T_FINAL), _state(e0), method="DOP853", rtol=1e-10, atol=1e-12, t_eval=ts
            )
            err = _zeta(sol.y.T) - np.stack([_reference_jet(t) for t in ts])
            dev = np.linalg.norm(err - E @ e0, axis=1)
            worst_dev = max(worst_dev, dev.max())
            least = min(least, np.abs(sol.y[3]).min())
            free = _loop(np.ones(2), np.full(2, np.inf))  # the law's own command, unclipped
            theta_dot = np.array([free(t, z)[2] for t, z in zip(ts, sol.y.T)])
            applied = np.abs(np.asarray(scale)[:, None] * np.stack([sol.y[3], theta_dot]))
            assert np.all(applied <= LIMIT[:, None])  # never saturates
        assert worst_dev <= mm["deviation_bound"]
        assert least >= EPS
        # what the bound costs: the largest simulated deviation against the proved one (0.59 of
        # it on 12 runs from the sphere at the corners of the range, 2026-11-28)
        assert worst_dev >= 0.25 * mm["deviation_bound"]


def test_a_torque_level_law_or_a_bad_range_is_refused():
    setting = _problem().setting("c")
    ctrl, params = setting.ctrl, setting.params()
    ok = C.Mismatch(LIMIT, (np.ones(2), np.ones(2)), (1.0, 1.0))
    with pytest.raises(ValueError, match="input_scale must be finite ends 0 < lo <= hi"):
        C.mismatch_radius(ctrl, params, ok._replace(input_scale=(np.ones(2), 0.5 * np.ones(2))), t_final=1.0, eps=EPS)
    with pytest.raises(ValueError, match=r"geometry_scale must be a \(lo, hi\) pair"):
        C.mismatch_radius(ctrl, params, ok._replace(geometry_scale=(1.0,)), t_final=1.0, eps=EPS)
    with pytest.raises(ValueError, match="input_limit must be > 0 per input"):
        C.mismatch_radius(ctrl, params, ok._replace(input_limit=np.array([1.0, 0.0])), t_final=1.0, eps=EPS)
    torque = _problem_at_torque().setting("c")
    with pytest.raises(ValueError, match="covers velocity-level laws"):
        C.mismatch_radius(torque.ctrl, torque.params(), ok, t_final=1.0, eps=EPS)


def _problem_at_torque():
    """The circle problem at torque level (the shared helper builds velocity-level ones)."""
    return Problem.from_dict(
        {
            "controller": {"law": "dynamic", "robot": "(2,0)", "level": "torque"},
            "reference": {"family": "circle"},
            "initial": {"space": "output", "x": 0.1},
            "simulation": {"t_final": 1.0, "dt": 0.02},
        }
    )


def test_a_product_over_two_balls_encloses_every_sampled_value():
    # x = 1 + 0.3 a1 + 0.2 b1, y = 2 + 0.4 a2 - 0.1 b2 with a, b in two unit disks
    g = jnp.array([[0.3, 0.0, 0.2, 0.0], [0.0, 0.4, 0.0, -0.1]])
    v = affine.symbols(jnp.array([1.0, 2.0]), g)
    f = lambda w: jnp.stack([w[0] * w[1], w[0] * w[0], jnp.sin(w[0] * w[1])])
    out, ctx = affine.enclose(f, v, n_ball=(2, 2))
    box = affine.to_interval(out, ctx)
    rng = np.random.default_rng(0)
    a, b = (rng.normal(size=(20000, 2)) for _ in range(2))
    a *= rng.uniform(size=(20000, 1)) ** 0.5 / np.linalg.norm(a, axis=1, keepdims=True)
    b *= rng.uniform(size=(20000, 1)) ** 0.5 / np.linalg.norm(b, axis=1, keepdims=True)
    pts = np.array([1.0, 2.0]) + np.concatenate([a, b], axis=1) @ np.asarray(g).T
    vals = np.asarray(jax.vmap(f)(pts))
    assert np.all(vals >= np.asarray(box.lo)) and np.all(vals <= np.asarray(box.hi))
    # four box symbols are a larger set than the two disks' product: never a narrower enclosure
    boxed, ctx0 = affine.enclose(f, v, n_ball=0)
    wide = affine.to_interval(boxed, ctx0)
    assert np.all(np.asarray(box.hi - box.lo) <= np.asarray(wide.hi - wide.lo) + 1e-12)
    with pytest.raises(ValueError, match="n_ball must be sizes >= 0 of at most 4 symbols"):
        affine.enclose(f, v, n_ball=(3, 2))
