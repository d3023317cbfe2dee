"""A new user's car (issue 58): a (1,1) car-like robot (L = 0.33 m, e = 0.25 m) on a waypoint
loop, forward and reverse, at velocity and torque level.

Two causes were behind its certification contradicting itself and refusing to drive forward:

- At torque level the (1,1) law's outputs P + e x1(theta) use the path's fifth derivative
  (through its heading), which a quintic spline does not keep continuous: the law's
  feed-forward jumped at every waypoint, RK4 followed it only to O(dt) (4.7e-4 on the loop
  below, dt = 0.01 s), and Lemma 2's bound (53) was "violated" by the integrator on every run.
  Sampled paths now get the spline degree the law needs (7 here, natural ends).
- The reference check is a compiled program, where the heading offset is traced and the
  reference's branch fell back to +1: every reference with offset pi (a car driving forward)
  was refused as reaching the singular set, with a regularity far from zero.

The oracle of the closed loop is ``expm``: from any initial error the simulated output error
must follow e^{At} e0 (the error dynamics the certificates are computed for).
"""

import jax
import jax.numpy as jnp
import numpy as np
import pytest
from scipy.interpolate import make_interp_spline
from scipy.linalg import expm

import wmrjax as w
from wmrjax import references as R
from wmrjax.problem import Problem, Space, Task, place

CAR = w.Geometry(L=0.33, e=0.25)


def ellipse_waypoints(n=17, a=6.0, b=3.0):
    """A loop of about 29 m through ``n`` waypoints (the first and last coincide in place)."""
    s = np.linspace(0.0, 2 * np.pi, n)
    return np.c_[a * np.sin(s), b - b * np.cos(s)]


def car_problem(tmp_path, level="torque", heading_offset=0.0, t_final=8.0):
    pts = ellipse_waypoints()
    text = f"""
[controller]
law = "dynamic"
robot = "(1,1)"
level = "{level}"
[geometry]
L = 0.33
e = 0.25
[reference]
family = "waypoints"
x = {pts[:, 0].tolist()}
y = {pts[:, 1].tolist()}
speed = 0.8
heading_offset = {heading_offset!r}
[initial]
space = "output"
x = {{ min = -0.3, max = 0.3, num = 2 }}
[simulation]
t_final = {t_final}
dt = 0.01
"""
    path = tmp_path / f"car_{level}_{heading_offset:.3f}.toml"
    path.write_text(text)
    return Problem.load(path)


def test_septic_spline_is_scipys_with_natural_ends():
    """Degree 7: SciPy's make_interp_spline with derivatives 4 to 6 zero at both ends, to rounding,
    every derivative up to 6 (sparse waypoints: the case where the end conditions matter)."""
    pts = ellipse_waypoints()
    ref = R.from_waypoints(pts, speed=0.8, degree=7)
    t = np.asarray(ref.params["t"])
    zero = np.zeros(2)
    ends = [(4, zero), (5, zero), (6, zero)]
    sp = make_interp_spline(t, pts, k=7, bc_type=(ends, ends))
    ts = np.linspace(0.0, t[-1], 301)
    got = np.asarray(jax.jit(jax.vmap(lambda s: R.taylor(ref.position, s, 6)))(jnp.asarray(ts)))
    for d in range(7):
        np.testing.assert_allclose(got[:, d], sp(ts, nu=d), atol=1e-9 * 10**d, err_msg=f"derivative {d}")
    # the fifth and sixth derivatives continuous across the interior knots (sixth: a kink only)
    knots = t[1:-1]
    left = np.asarray(jax.vmap(lambda s: R.taylor(ref.position, s, 6))(jnp.asarray(knots - 1e-9)))
    right = np.asarray(jax.vmap(lambda s: R.taylor(ref.position, s, 6))(jnp.asarray(knots + 1e-9)))
    assert np.abs(left[:, 5] - right[:, 5]).max() < 1e-6
    # and the quintic default's fifth derivative does jump there (what made the feed-forward jump)
    q = R.from_waypoints(pts, speed=0.8)
    ql = np.asarray(jax.vmap(lambda s: R.taylor(q.position, s, 5))(jnp.asarray(knots - 1e-9)))
    qr = np.asarray(jax.vmap(lambda s: R.taylor(q.position, s, 5))(jnp.asarray(knots + 1e-9)))
    assert np.abs(ql[:, 5] - qr[:, 5]).max() > 1e-2


def test_spline_degree_follows_the_law():
    assert w.dynamic_linearization("(1,1)", level="torque").path_order == 5
    assert w.dynamic_linearization("(1,1)", level="velocity").path_order == 4
    assert R.spline_degree_for(4) == 5 and R.spline_degree_for(5) == 7
    with pytest.raises(ValueError, match="degree > 7"):
        R.spline_degree_for(7)
    with pytest.raises(ValueError, match="degree must be one of"):
        R.from_waypoints(ellipse_waypoints(), degree=6)
    with pytest.raises(ValueError, match="at least 8 samples"):
        R.from_waypoints(ellipse_waypoints(7), degree=7)


@pytest.mark.parametrize("level,degree", [("torque", 7), ("velocity", 5)])
def test_problem_builds_the_spline_its_law_needs(tmp_path, level, degree):
    s = car_problem(tmp_path, level=level).setting("certification")
    assert s.params().reference.params["pp"].shape[-2] == degree + 1


def _deviation_from_error_dynamics(ctrl, params, branch, t_final, dt=0.01, seed=0):
    """max_t || error(t) - e^{At} e0 || over three runs from random initial errors of norm 0.2."""
    A = np.asarray(ctrl.error_matrix(params.gains))
    rng = np.random.default_rng(seed)
    e0s = rng.normal(size=(3, A.shape[0]))
    e0s *= 0.2 / np.linalg.norm(e0s, axis=1, keepdims=True)
    n = int(round(t_final / dt))

    def run(e0):
        z0 = place(ctrl, params, e0, Space.OUTPUT, Task.POSTURE, branch)
        tr = w.simulate(ctrl, z0, params, dt=dt, n_steps=n, save_every=10, error_tol=np.inf)
        return tr.t, jax.vmap(lambda t, z: ctrl.error(t, z, params).reshape(-1))(tr.t, tr.state), tr.diagnostics.failed

    ts, errs, failed = jax.jit(jax.vmap(run))(jnp.asarray(e0s))
    assert not np.any(failed)
    ts = np.asarray(ts[0])
    want = np.stack([np.stack([expm(A * t) @ e0 for t in ts]) for e0 in e0s])
    return float(np.abs(np.asarray(errs) - want).max())


@pytest.mark.parametrize("level", ["torque", "velocity"])
@pytest.mark.parametrize("heading_offset", [0.0, np.pi], ids=["reverse", "forward"])
def test_car_follows_the_certified_error_dynamics(tmp_path, level, heading_offset):
    """The user's car, shortened to 12 s (five waypoints passed): the simulated error is e^{At} e0
    to 1e-6 (on the whole 36 s loop from errors of norm 0.1: 1.4e-9 at torque level, against 4.7e-4
    with the quintic path it had before; heading offset pi was refused then)."""
    s = car_problem(tmp_path, level=level, heading_offset=heading_offset, t_final=12.0).setting("certification")
    ctrl, params = s.ctrl, s.params()
    branch = ctrl.reference_branch(params)
    assert branch == (-1 if heading_offset else 1)
    assert _deviation_from_error_dynamics(ctrl, params, branch, 12.0) < 1e-6


def test_forward_car_drives_forward(tmp_path):
    """Heading offset pi: the car's steering wheel leads (the body's -x2 is the direction of travel)
    and its rear axle's speed along the path is positive, for e = 0.25 m."""
    s = car_problem(tmp_path, level="velocity", heading_offset=np.pi).setting("certification")
    ctrl, params = s.ctrl, s.params()
    z = np.asarray(jax.vmap(lambda t: ctrl.reference_state(t, params))(jnp.linspace(0.0, 8.0, 9)))
    theta, beta, eta1 = z[:, 2], z[:, 3], z[:, 4]
    # speed of P along x2 is L eta1 sin(beta) (concepts page): negative, i.e. moving along -x2
    assert np.all(CAR.L * eta1 * np.sin(beta) < 0)
    vel = np.asarray(jax.vmap(params.reference.velocity)(jnp.linspace(0.0, 8.0, 9)))
    forward = np.stack([-np.cos(theta + np.pi / 2), -np.sin(theta + np.pi / 2)], axis=1)  # world -x2
    assert np.all(np.sum(vel * forward, axis=1) > 0.5)


def test_other_branch_message_names_the_key(tmp_path):
    """A regular reference on the other branch than its offset is refused with the condition and
    the key, not as 'reaches the singular set'. Built by hand: a traced check is not needed."""
    ctrl = w.dynamic_linearization("(1,1)")
    ref = R.from_waypoints(ellipse_waypoints(), speed=0.8, heading_offset=np.pi)
    params = ctrl.params(ref, poles=1.0, geometry=CAR)
    ts = np.linspace(0.0, 1.0, 5)
    jets = np.zeros((5, 4, 2))
    with pytest.raises(ValueError, match=r"other branch.*heading_offset"):
        ctrl._judge_reference(params, (ts, jets, np.full(5, 0.3), np.full(5, 0.4)), 0.0, 1.0, 1e-6)
    with pytest.raises(ValueError, match="at or below the floor"):
        ctrl._judge_reference(params, (ts, jets, np.full(5, 1e-9), np.full(5, -0.4)), 0.0, 1.0, 1e-6)


def _sampled_path(kind, degree):
    """The ellipse's waypoints, or a lane change sampled at 10 Hz, as a spline of ``degree``."""
    if kind == "waypoints":
        return R.from_waypoints(ellipse_waypoints(), speed=0.8, degree=degree)
    t = np.arange(0.0, 12.05, 0.1)
    return R.from_samples(t, np.c_[t, 1.5 * np.tanh(t - 5.0)], degree=degree)


# each type at both levels, each level on both paths: (type, level) pairs on one path each, the
# path alternating (the 16 pairs x paths took 118 CPU s of the make-test budget; half of them here)
PAIRS = [
    ("(2,0)", "velocity", "waypoints"),
    ("(2,0)", "torque", "samples"),
    ("(2,1)", "velocity", "samples"),
    ("(2,1)", "torque", "waypoints"),
    ("(1,1)", "velocity", "waypoints"),
    ("(1,1)", "torque", "samples"),
    ("(1,2)", "velocity", "samples"),
    ("(1,2)", "torque", "waypoints"),
]


@pytest.mark.parametrize("robot, level, path", PAIRS)
def test_every_type_and_level_follows_its_error_dynamics_on_sampled_paths(robot, level, path):
    """Every Table 4 row at both levels, on a waypoint or a sampled path (each level of each type
    on one, both paths for every type and every level), with the spline degree a problem file
    would choose for it: the simulated error is e^{At} e0 to 1e-6 over 8 s."""
    row = w.controllers.TABLE4[robot]
    ctrl = w.dynamic_linearization(robot, level=level)
    ref = _sampled_path(path, R.spline_degree_for(ctrl.path_order)).with_heading_offset(row.default_heading_offset)
    params = ctrl.params(ref, poles=1.0, geometry=row.default_geometry)
    dev = _deviation_from_error_dynamics(ctrl, params, ctrl.reference_branch(params), 8.0)
    assert dev < 1e-6, (robot, level, path, dev)


def test_quintic_waypoints_refused_at_torque_level_with_the_fix():
    """Built by hand with the quintic default, the torque-level car's path is refused by the
    reference check (its fourth output derivative jumps), and the message gives the degree."""
    ctrl = w.dynamic_linearization("(1,1)", level="torque")
    params = ctrl.params(R.from_waypoints(ellipse_waypoints(), speed=0.8), poles=1.0, geometry=CAR)
    with pytest.raises(ValueError, match=r"order 4 jumps.*degree=7"):
        ctrl.check_reference(params, 12.0)


@pytest.mark.parametrize("degree", [5, 7])
def test_extrapolation_is_bounded_and_smooth_at_the_join(degree):
    """extrapolate=True (the too-short-path message's fix): before, the end polynomial put this
    lane change 13 m off at 14.8 m/s at 8 s (measured at bd57cac); now the path tends to the end's
    straight line at the end's velocity, every derivative below the degree continuous at both joins."""
    t = np.arange(0.0, 4.0 + 1e-9, 0.05)
    xy = np.c_[t, 1.5 * np.tanh(2.0 * (t - 2.0))]
    ref = R.from_samples(t, xy, extrapolate=True, degree=degree)
    jets = jax.jit(jax.vmap(lambda s: R.taylor(ref.position, s, degree)))
    for end in (0.0, 4.0):
        a, b = np.asarray(jets(jnp.array([end - 1e-9, end + 1e-9])))
        # 2e-9 s apart: what differs is that step times the next derivative (up to 5e3 here)
        np.testing.assert_allclose(a[:degree], b[:degree], atol=1e-4)
    far = np.asarray(jets(jnp.array([12.0, 40.0, -8.0])))
    end_velocity = np.asarray(jets(jnp.array([4.0])))[0, 1]
    np.testing.assert_allclose(far[0, 1], end_velocity, atol=1e-12)  # 8 s on: the end's velocity
    np.testing.assert_allclose(far[1, 0], np.asarray(ref.position(4.0)) + 36.0 * end_velocity, atol=1e-9)
    outside = jnp.concatenate([jnp.linspace(-8.0, 0.0, 801), jnp.linspace(4.0, 40.0, 3601)])
    speeds = np.linalg.norm(np.asarray(jets(outside))[:, 1], axis=1)
    assert speeds.max() < 1.01 * np.linalg.norm(end_velocity)  # measured: the end speed, 1.000008 m/s


def test_falsifier_takes_the_exact_maps_worst_error_when_its_search_ends_above_it():
    """On the tuned car the falsifier's local search ended at 0.952 where the exact map's worst
    error fails from 0.925, and the alarm called one of them wrong. A search result above the
    exact-map radius is now checked at that error (dt / 10): here made by hand, 1.5 times the
    radius; the confirmed failure at 1.001 times replaces it, and a result within 0.1 % stays."""
    from wmrjax.certify import exact_map_radius
    from wmrjax.certify.falsify import FalsifiedRadius
    from wmrjax.certify.pipeline import _confirm_exact_worst

    ctrl = w.dynamic_linearization("(2,0)")
    params = ctrl.params(R.circle(radius=2.0, omega=0.5), poles=1.0, geometry=w.Geometry(e=0.2))
    horizon = dict(t_final=6.0, eps=0.01)
    exact = exact_map_radius(ctrl, params, basis="position", **horizon)
    r = float(exact.radius)
    loose = FalsifiedRadius(1.5 * r, None, None, 100, (r, 1.5 * r), 1.5 * r, {"gradient": 100}, None)
    got = _confirm_exact_worst(ctrl, params, loose, exact, dt=0.01, log=lambda *_: None, **horizon)
    np.testing.assert_allclose(got.radius, 1.001 * r, rtol=1e-12)
    assert got.distance < 0.01 and got.rollouts == 104 and got.rollouts_by_stage["exact_map_worst"] == 4
    np.testing.assert_allclose(np.linalg.norm(got.initial_error), 1.001 * r, rtol=1e-12)
    tight = loose._replace(radius=1.0005 * r)
    assert _confirm_exact_worst(ctrl, params, tight, exact, dt=0.01, log=lambda *_: None, **horizon) is tight


def test_uneven_samples_find_their_piece_without_a_loop():
    """Waypoints are timed by chord length (uneven samples): their piece was found by a binary
    search, a scan the C generator cannot hold, and every waypoint problem's export failed. The
    index by comparisons equals the search's, and the car's step now generates C."""
    from wmrjax import export as X

    ts = jnp.asarray(np.cumsum(np.r_[0.0, np.random.default_rng(1).uniform(0.1, 1.0, 40)]))
    s = jnp.linspace(-1.0, float(ts[-1]) + 1.0, 2001)
    got = jax.vmap(lambda x: R._piece(ts, x, uniform=False))(s)
    want = jnp.clip(jnp.searchsorted(ts, s, side="right") - 1, 0, ts.shape[0] - 2)
    np.testing.assert_array_equal(np.asarray(got), np.asarray(want))
    ctrl = w.dynamic_linearization("(1,1)", level="velocity")
    ref = R.from_waypoints(ellipse_waypoints(), speed=0.8, heading_offset=np.pi)
    step = X.control_step(ctrl, ctrl.params(ref, poles=1.0, geometry=CAR))
    assert "wmr_11_velocity_step" in X.generate_c(step)["wmr_11_velocity.c"]
