"""The mismatch radius: a proved bound of the real loop's deviation from the nominal one under an
input-scale range, and the radius it certifies (issue 54, item 3, continuous loop).

Oracles: the (2,0) law at e = 0 along a circle written here (its output jet, its command and the
plant with scaled, clipped inputs), SciPy's ``expm`` and DOP853 integrations of that plant at the
corners of the scale range and inside it, from initial errors on the proved sphere.
"""

from __future__ import annotations

import functools

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


# --- the zero-order hold (a digital controller) ------------------------------------------------

PERIOD = 0.05  # [s]: a 20 Hz controller


def _law_at(t, z):
    """The circle law written here at state z = (x, y, theta, chi) and time t: the plant command
    (chi, theta') and the compensator's rate chi' (poles -1, -1: v = ref'' - 2 e' - e)."""
    x, y, th, chi = z
    s, c = np.sin(th), np.cos(th)
    ref = _reference_jet(t)
    v = -(OMEGA**2) * ref[:2] - 2.0 * (chi * np.array([-s, c]) - ref[2:]) - (np.array([x, y]) - ref[:2])
    return np.array([chi, -(c * v[0] + s * v[1]) / chi]), -s * v[0] + c * v[1]


def _held_rate(t, z, u_k, a_k):
    """d/dt of the output error of the held loop at state z (compensator interpolated): the plant
    integrates the held (chi_k, omega_k), the compensator advances at the held rate a_k."""
    x, y, th, chi = z
    s, c = np.sin(th), np.cos(th)
    zeta_dot = np.array([-u_k[0] * s, u_k[0] * c, -a_k * s - chi * c * u_k[1], a_k * c - chi * s * u_k[1]])
    ref_dot = np.concatenate([_reference_jet(t)[2:], -(OMEGA**2) * _reference_jet(t)[:2]])
    return zeta_dot - ref_dot


@functools.partial(jax.jit, static_argnums=0)
def _quadrature(ctrl, params, jet_t, err_t, d_jet, d_err, lam, w):
    """The mean value form's integral over lambda by the Gauss-Legendre rule (nodes ``lam``,
    weights ``w``): one program for every node (op by op, the 24 nodes took 38 s)."""
    rate = lambda lm: C.hold_rate(
        ctrl, params, jet_t, err_t, jnp.ones(2), 1.0, (d_jet, d_err), (jet_t - lm * d_jet, -lm * d_err)
    )
    return w @ jax.vmap(rate)(lam)


def test_the_hold_rate_is_the_held_loops_error_rate_less_a_zeta():
    """Delta_hold (mean value form, Gauss-Legendre over lambda) equals zeta_err' - A zeta_err of the
    held loop written here, between a sample and a later time of the period."""
    setting = _problem().setting("c")
    ctrl, params = setting.ctrl, setting.params()
    nodes, weights = np.polynomial.legendre.leggauss(24)
    lam, w = 0.5 * (nodes + 1), 0.5 * weights
    jet_at = lambda t: np.asarray(ctrl.reference_jet(t, params)[:3])
    rng = np.random.default_rng(7)
    for _ in range(4):
        t_k = rng.uniform(0.0, T_FINAL - PERIOD)
        t = t_k + rng.uniform(0.0, PERIOD)
        err_k, err_t = 0.2 * rng.normal(size=4), 0.2 * rng.normal(size=4)
        u_k, a_k = _law_at(t_k, _state_at(t_k, err_k))
        want = _held_rate(t, _state_at(t, err_t), u_k, a_k) - A @ err_t
        jet_t, d_jet, d_err = jet_at(t), jet_at(t) - jet_at(t_k), err_t - err_k
        got = np.asarray(_quadrature(ctrl, params, jet_t, err_t, d_jet, d_err, lam, w))
        assert got == pytest.approx(want, abs=1e-9)
        u, a = (np.asarray(x) for x in C.sampled_inputs(ctrl, params, jet_at(t_k), jnp.asarray(_state_at(t_k, err_k))))
        assert np.allclose(u, u_k, atol=1e-12) and np.allclose(a, a_k, atol=1e-12)


def test_a_held_box_encloses_the_held_loops_deviation_rate():
    """One period's enclosure of ||Delta|| (the sample's command, the hold, the error's change over
    the period) holds every value of the held loop written here, run by DOP853 over the first
    period from initial errors on the sphere of radius 0.05, and is within a stated factor of it."""
    setting = _problem().setting("c")
    ctrl, params = setting.ctrl, setting.params()
    rho, rng = 0.05, np.random.default_rng(3)
    dirs = rng.normal(size=(24, 4))
    dirs /= np.linalg.norm(dirs, axis=1, keepdims=True)
    ts = np.linspace(0.0, PERIOD, 26)
    worst, dev = 0.0, 0.0
    for d in dirs:
        e0 = rho * d
        u_k, a_k = _law_at(0.0, _state(e0))
        held = lambda t, z: [-u_k[0] * np.sin(z[2]), u_k[0] * np.cos(z[2]), u_k[1], a_k]
        sol = scipy.integrate.solve_ivp(
            held, (0.0, PERIOD), _state(e0), method="DOP853", rtol=1e-11, atol=1e-12, t_eval=ts
        )
        for t, z in zip(ts, sol.y.T):
            err = _zeta(z) - _reference_jet(t)
            worst = max(worst, np.linalg.norm(_held_rate(t, z, u_k, a_k) - A @ err))
            dev = max(dev, np.linalg.norm(err - scipy.linalg.expm(A * t) @ e0))
    m = C.Mismatch(np.full(2, np.inf), (np.ones(2), np.ones(2)), (1.0, 1.0), period=PERIOD)
    m = C.deviation.check_mismatch(ctrl, params, m)
    with jax.disable_jit():  # one box: its eager evaluation is far cheaper than compiling the program
        tube = C.deviation._Tube(ctrl, False, params, np.eye(4), m, PERIOD, 1)
        bound, fits = tube.rate(rho, 1.5 * dev, 1.5 * worst)
    assert fits
    assert np.isfinite(bound) and worst <= bound
    # what the enclosure costs on this box: the sampled largest ||Delta|| is 0.15 of the bound
    # (0.0104 vs 0.0688, 2026-11-29); it grows fast with the radius (0.24 at 0.1, inf at 0.2)
    assert worst >= 0.1 * bound, (worst, bound)


def test_a_bad_period_or_noise_is_refused():
    setting = _problem().setting("c")
    ctrl, params = setting.ctrl, setting.params()
    ok = C.Mismatch(LIMIT, (np.ones(2), np.ones(2)), (1.0, 1.0))
    check = lambda m: C.deviation.check_mismatch(ctrl, params, m)
    with pytest.raises(ValueError, match=r"period must be finite and >= 0 \[s\]"):
        check(ok._replace(period=-0.05))
    with pytest.raises(ValueError, match="period must be a number of seconds"):
        check(ok._replace(period="0.05"))
    with pytest.raises(ValueError, match="noise needs a controller period"):
        check(ok._replace(noise=(0.01, 0.01, 0.0)))
    with pytest.raises(ValueError, match=r"noise must be at most 3 finite bounds >= 0"):
        check(ok._replace(period=0.05, noise=(0.01, -0.01)))
    m = check(ok._replace(period=0.05, noise=(0.03, 0.03)))
    assert m.period == 0.05 and m.noise.tolist() == [0.03, 0.03, 0.0]
