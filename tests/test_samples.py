"""References from the user's own samples: the quintic spline against SciPy and the exact
path, its derivatives, its gradients, its errors; a sampled polynomial plan tracked as well
as the exact one."""

import dataclasses

import jax
import jax.numpy as jnp
import numpy as np
import pytest
from scipy.interpolate import make_interp_spline

import wmrjax as w
from wmrjax import references as R

T = np.linspace(0.0, 20.0, 400)


@pytest.fixture(scope="module")
def circle():
    exact = R.circle(radius=2.0, omega=0.5)
    xy = np.asarray(jax.vmap(exact.position)(jnp.asarray(T)))
    return exact, xy, R.from_samples(T, xy)


def _jets(ref, ts, order):
    return np.asarray(jax.jit(jax.vmap(lambda s: R.taylor(ref.position, s, order)))(jnp.asarray(ts)))


def test_circle_position_and_third_derivative(circle):
    exact, xy, ref = circle
    ts = np.linspace(0.013, 19.99, 777)
    got, want = _jets(ref, ts, 4), _jets(exact, ts, 4)
    assert np.abs(got[:, 0] - want[:, 0]).max() < 1e-6  # the bound: 1e-6 m
    rel3 = np.linalg.norm(got[:, 3] - want[:, 3], axis=1) / np.linalg.norm(want[:, 3], axis=1)
    assert rel3.max() < 1e-2  # and 1 % on the third derivative
    assert np.abs(got[:, 0] - want[:, 0]).max() < 1e-10  # measured: 6e-12
    assert rel3.max() < 1e-4  # measured: 1.4e-5
    # the fourth derivative (torque-level dynamic laws) is continuous across the knots
    knots = T[3:-3]
    left = _jets(ref, knots - 1e-9, 4)[:, 4]
    right = _jets(ref, knots + 1e-9, 4)[:, 4]
    assert np.abs(left - right).max() < 1e-6


def test_same_spline_as_scipy(circle):
    _, xy, ref = circle
    sp = make_interp_spline(T, xy, k=5)
    ts = np.linspace(0.0, 20.0, 501)
    np.testing.assert_allclose(_jets(ref, ts, 0)[:, 0], sp(ts), atol=1e-13)
    np.testing.assert_allclose(_jets(ref, ts, 3)[:, 3], sp.derivative(3)(ts), atol=1e-8)


def test_piece_lookup_on_an_even_grid_equals_the_search():
    """Samples at a nearly constant rate take the grid's piece index (corrected by one comparison
    each side) instead of a binary search: the same piece, so the same jets to the last bit, at
    the samples themselves, between them and past both ends; jittered times (a tenth of a step)
    still count as even, a sample out of place by half a step does not."""
    rng = np.random.default_rng(3)
    t = np.arange(0.0, 10.0 + 1e-9, 0.05) + rng.uniform(-0.005, 0.005, 201)
    xy = np.stack([np.cos(t), np.sin(2 * t)], axis=1)
    even = R.from_samples(t, xy, extrapolate=True)
    assert even.path is R._path_spline_uniform_extrapolated
    searched = dataclasses.replace(even, path=R._path_spline_extrapolated)
    ts = np.concatenate([t, (t[:-1] + t[1:]) / 2, np.nextafter(t, -np.inf), [-0.3, 10.4]])
    np.testing.assert_array_equal(_jets(even, ts, 4), _jets(searched, ts, 4))
    uneven = t.copy()
    uneven[100] += 0.5 * 0.05 * 0.9  # the grid's guess can be off by one here, the search is used
    uneven[101] += 0.5 * 0.05
    assert R.from_samples(uneven, xy).path is R._path_spline


def test_a_sampled_path_held_as_numpy_arrays_evaluates_under_jit(circle):
    """A problem holds its references' params as NumPy arrays (the tuner did, and indexing them by
    a traced piece index raised TracerArrayConversionError): the same values as the JAX-held path."""
    _, _, ref = circle
    held = dataclasses.replace(ref, params=jax.tree_util.tree_map(np.asarray, ref.params))
    ts = np.linspace(0.0, 20.0, 41)
    np.testing.assert_array_equal(_jets(held, ts, 3), _jets(ref, ts, 3))


def test_gradient_wrt_samples_and_times_matches_finite_differences():
    t = np.linspace(0.0, 5.0, 12)
    xy = np.stack([t, np.sin(t)], axis=1)

    def f(t, xy):
        ref = R.from_samples(t, xy)
        return ref.position(jnp.asarray(2.2))[1] + 0.3 * ref.velocity(jnp.asarray(3.1))[0]

    gt, gx = jax.grad(f, argnums=(0, 1))(jnp.asarray(t), jnp.asarray(xy))
    h = 1e-6
    for i in (0, 4, 7):
        dt = np.zeros_like(t)
        dt[i] = h
        fd = (f(jnp.asarray(t + dt), jnp.asarray(xy)) - f(jnp.asarray(t - dt), jnp.asarray(xy))) / (2 * h)
        np.testing.assert_allclose(gt[i], fd, rtol=1e-6, atol=1e-8)
        dx = np.zeros_like(xy)
        dx[i, 1] = h
        fd = (f(jnp.asarray(t), jnp.asarray(xy + dx)) - f(jnp.asarray(t), jnp.asarray(xy - dx))) / (2 * h)
        np.testing.assert_allclose(gx[i, 1], fd, rtol=1e-6, atol=1e-8)
    # the spline is linear in the samples: the weights of one evaluation sum to one
    np.testing.assert_allclose(
        float(jnp.sum(jax.grad(lambda v: R.from_samples(t, v).position(2.2)[1])(jnp.asarray(xy))[:, 1])),
        1.0,
        rtol=1e-12,
    )


@pytest.mark.parametrize(
    "t, xy, match",
    [
        ([0.0, 1.0, 1.0, 2.0, 3.0, 4.0], np.zeros((6, 2)), "strictly increasing"),
        ([0.0, 1.0, 2.0, 3.0, 4.0], np.zeros((5, 2)), "at least 6 samples"),
        (np.arange(6.0), np.zeros((6, 3)), r"shape \(6, 2\)"),
        (np.arange(6.0), np.zeros((7, 2)), r"shape \(6, 2\)"),
        (np.arange(6.0)[:, None], np.zeros((6, 2)), "1-D"),
        ([0.0, 1.0, np.nan, 3.0, 4.0, 5.0], np.zeros((6, 2)), "non-finite"),
    ],
)
def test_bad_samples(t, xy, match):
    with pytest.raises(ValueError, match=match):
        R.from_samples(np.asarray(t), xy)


def test_a_path_that_stops_is_refused_with_min_speed():
    t = np.linspace(0.0, 6.0, 31)
    xy = np.stack([(t - 3.0) ** 3 / 9.0, np.zeros_like(t)], axis=1)  # speed (t - 3)^2 / 3: stops at 3 s
    with pytest.raises(ValueError, match=r"slows to .* at t = 3 s, below min_speed = 0.05"):
        R.from_samples(t, xy, min_speed=0.05)
    R.from_samples(t, xy)  # without a floor it is a valid point-tracking path


def test_waypoints_and_csv(tmp_path):
    ang = np.linspace(0.0, np.pi, 40)
    pts = np.stack([3 * np.cos(ang), 3 * np.sin(ang)], axis=1)
    ref = R.from_waypoints(pts, speed=1.5)
    chord = 2 * 3 * np.sin(np.pi / 39 / 2)
    tv = np.arange(40) * chord / 1.5
    np.testing.assert_allclose(np.asarray(jax.vmap(ref.position)(jnp.asarray(tv))), pts, atol=1e-12)
    speeds = np.asarray(jax.vmap(ref.speed)(jnp.linspace(0.5, tv[-1] - 0.5, 50)))
    np.testing.assert_allclose(speeds, 1.5 * (np.pi / 39 * 3) / chord, rtol=1e-4)  # arc speed of the chord timing
    with pytest.raises(ValueError, match="waypoints 3 and 4 coincide"):
        R.from_waypoints(np.concatenate([pts[:4], pts[3:]]))
    path = tmp_path / "plan.csv"
    path.write_text("# a plan\nt,x,y,vx\n" + "\n".join(f"{a},{b},{c},0" for a, (b, c) in zip(tv, pts)))
    loaded = R.load_samples(path)
    assert loaded.name == "plan"
    np.testing.assert_allclose(
        np.asarray(loaded.position(jnp.asarray(1.234))), np.asarray(ref.position(jnp.asarray(1.234))), atol=1e-13
    )
    (tmp_path / "bad.csv").write_text("time,x,y\n0,0,0\n")
    with pytest.raises(ValueError, match=r"missing column\(s\) \['t'\]"):
        R.load_samples(tmp_path / "bad.csv")
    # a duplicated column used the last one; a device was read without bound; a BOM was refused
    (tmp_path / "dup.csv").write_text("t,x,y,x\n0,0,0,5\n1,1,0,6\n")
    with pytest.raises(ValueError, match=r"column\(s\) \['x'\] appear more than once"):
        R.load_samples(tmp_path / "dup.csv")
    with pytest.raises(ValueError, match="'/dev/zero': not a regular file"):
        R.load_samples("/dev/zero")
    (tmp_path / "bom.csv").write_bytes("\ufeff# a plan\nt,x,y,vx\n".encode() + path.read_bytes().split(b"vx\n", 1)[1])
    np.testing.assert_allclose(
        np.asarray(R.load_samples(tmp_path / "bom.csv").position(jnp.asarray(1.234))),
        np.asarray(loaded.position(jnp.asarray(1.234))),
        rtol=0,
        atol=0,
    )


def _lane_change(t, params):
    """A python-control-style point-to-point plan: x at 2 m/s, y a quintic from 0 to 3.5 m over 8 s."""
    s = t / 8.0
    return jnp.stack([2.0 * t, 3.5 * (10 * s**3 - 15 * s**4 + 6 * s**5)])


def test_sampled_plan_is_tracked_as_well_as_the_exact_one():
    exact = R.from_function(_lane_change, name="lane_change")
    t = np.linspace(0.0, 8.0, 81)
    sampled = R.from_samples(t, np.asarray(jax.vmap(exact.position)(jnp.asarray(t))), min_speed=0.5)
    ctrl = w.dynamic_linearization("(2,0)", "velocity")
    out = []
    for ref in (exact, sampled):
        p = ctrl.params(ref, poles=1.0, geometry=w.Geometry(e=0.0))
        z0 = ctrl.reference_state(0.0, p).at[0].add(0.3).at[1].add(-0.2)
        tr = w.simulate(ctrl, z0, p, dt=0.01, n_steps=800, save_every=800)
        assert not bool(tr.diagnostics.failed)
        out.append(np.asarray(tr.final_state[:2]) - np.asarray(exact.position(jnp.asarray(8.0))))
    err_exact, err_sampled = (np.hypot(*e) for e in out)
    assert err_exact < 0.02
    assert abs(err_sampled - err_exact) < 1e-5


def _circle_on_0_4():
    """A circle sampled at 20 Hz on [0, 4] s and the (2,0) velocity-level loop on it:
    ``(circle, ts, xy, ctrl, params, z0 on the reference)``."""
    circ = R.circle(radius=2.0, omega=0.5)
    ts = np.linspace(0.0, 4.0, 81)
    xy = np.asarray(jax.vmap(circ.position)(jnp.asarray(ts)))
    ctrl = w.dynamic_linearization("(2,0)", "velocity")
    p = ctrl.params(R.from_samples(ts, xy), poles=1.0, geometry=w.Geometry())
    return circ, ts, xy, ctrl, p, ctrl.reference_state(0.0, p)


def test_a_traced_horizon_outside_the_samples_fails_the_run():
    """Under jit or vmap the horizon is not known before compiling, so simulate cannot refuse it:
    a run whose [t0, t0 + n dt] leaves the samples fails at t0 instead (it ran past them without a
    word before: failed = False, 0.2 m off the sampled circle). Runs inside the samples in the same
    batch are unchanged (the same final state as an eager run), and an extrapolated path runs on."""
    circ, ts, xy, ctrl, p, z0 = _circle_on_0_4()
    run = lambda t0, dt, pp=p: w.simulate(ctrl, z0, pp, dt=dt, n_steps=400, save_every=400, t0=t0)
    past = jax.jit(run)(0.0, 0.02)  # to 8 s
    assert bool(past.diagnostics.failed) and float(past.diagnostics.t_failure) == 0.0
    np.testing.assert_array_equal(past.final_state, z0)  # frozen at the start
    both = jax.vmap(run, in_axes=(0, None))(jnp.array([0.0, 4.0, -0.5]), 0.01)  # [0, 4], [4, 8], [-0.5, 3.5]
    assert np.asarray(both.diagnostics.failed).tolist() == [False, True, True]
    np.testing.assert_allclose(both.final_state[0], run(0.0, 0.01).final_state, rtol=0, atol=1e-13)
    pe = ctrl.params(R.from_samples(ts, xy, extrapolate=True), poles=1.0, geometry=w.Geometry())
    assert not bool(jax.jit(lambda dt: run(0.0, dt, pe))(0.02).diagnostics.failed)


def test_a_horizon_outside_the_samples_is_refused_unless_extrapolated(tmp_path, monkeypatch):
    """Circle samples on [0, 4] s: a run to 8 s, a run from t0 = -1 s, the reference check and a
    Lemma 2 certificate over 8 s are refused by name; with extrapolate=True the run goes on (the
    path then tends to the tangent line at the last sample's velocity, off the circle at 8 s); samples on [5, 25] s refuse a horizon starting at 0. The problem file's key too."""
    from wmrjax import certify as C
    from wmrjax.problem import Problem, ProblemError

    circ, ts, xy, ctrl, p, z0 = _circle_on_0_4()
    lo, hi = p.reference.domain()
    assert float(lo) == 0.0 and float(hi) == 4.0 and circ.domain() is None
    with pytest.raises(
        ValueError, match=r"defined by its samples on \[0, 4\] s, and the horizon \[0, 8\] s goes past its last"
    ):
        w.simulate(ctrl, z0, p, dt=0.01, n_steps=800)
    with pytest.raises(ValueError, match=r"goes before its first sample"):
        w.simulate(ctrl, z0, p, dt=0.01, n_steps=100, t0=-1.0)
    with pytest.raises(ValueError, match="extrapolate=True"):
        ctrl.check_reference(p, 8.0)
    with pytest.raises(ValueError, match="past its last sample"):
        C.lemma2(ctrl, p, t_final=8.0, eps=1e-2)
    assert not bool(w.simulate(ctrl, z0, p, dt=0.01, n_steps=400).diagnostics.failed)  # [0, 4] s: inside
    pe = ctrl.params(R.from_samples(ts, xy, extrapolate=True), poles=1.0, geometry=w.Geometry())
    assert pe.reference.domain() is None
    tr = w.simulate(ctrl, z0, pe, dt=0.01, n_steps=800, save_every=800)
    off = float(jnp.linalg.norm(pe.reference.position(8.0) - circ.position(8.0)))
    assert not bool(tr.diagnostics.failed) and off > 0.1
    late = R.from_samples(ts * 5.0 + 5.0, xy)
    with pytest.raises(ValueError, match=r"on \[5, 25\] s, and the horizon \[0, 10\] s goes before its first"):
        ctrl.check_reference(ctrl.params(late, poles=1.0, geometry=w.Geometry()), 10.0)
    with pytest.raises(ValueError, match="extrapolate must be True or False"):
        R.from_samples(ts, xy, extrapolate="yes")
    data = {
        "controller": {"law": "dynamic", "robot": "(2,0)"},
        "reference": {"family": "samples", "t": ts.tolist(), "x": xy[:, 0].tolist(), "y": xy[:, 1].tolist()},
        "initial": {"space": "output"},
        "simulation": {"t_final": 8.0, "dt": 0.01},
    }
    with pytest.raises(ProblemError, match="past its last sample"):
        Problem.from_dict(data)
    # refused on the sample times, before the spline is solved (the probe's samples-problem-past-end
    # was POOR: the banded solve's scan was traced first, a late refusal)
    with monkeypatch.context() as m:
        unbuilt = dataclasses.replace(R.FAMILIES["samples"], make=lambda *a, **k: pytest.fail("the spline was built"))
        m.setitem(R.FAMILIES, "samples", unbuilt)
        with pytest.raises(ProblemError, match=r"\[reference\] \('t', 'x', 'y'\): reference 'samples' is defined"):
            Problem.from_dict(data)
    data["reference"]["extrapolate"] = True
    assert Problem.from_dict(data).settings()[0].reference.domain() is None
    data["reference"]["extrapolate"] = "yes"
    with pytest.raises(ProblemError, match=r"\[reference\] extrapolate: expected true or false"):
        Problem.from_dict(data)


def test_kink_message_names_the_likely_cause():
    """A failed kink test named every cause 'a kink or corner'; the message now tells clock
    times (epoch seconds) and a path that stops from a corner (float32 round-off is told by
    the default float type, checked here by its absence)."""
    from wmrjax.controllers.law import kink_cause

    ts = np.linspace(0.0, 10.0, 101)
    moving = np.zeros((101, 3, 2))
    moving[:, 1, 0] = 1.0
    assert kink_cause(ts, moving) == "a kink or corner in the path"
    assert "clock readings (epoch seconds)" in kink_cause(ts + 1.7e9, moving)
    stops = moving.copy()
    stops[50, 1, 0] = 0.0
    assert "the path stops: its speed falls to 0 m/s at t = 5 s" in kink_cause(ts, stops)


def test_min_speed_on_traced_samples_warns():
    """from_samples(min_speed=) under jit cannot check traced samples: it says so (a warning)
    instead of skipping the check silently, and the path it builds is the eager one."""
    t = jnp.linspace(0.0, 6.0, 13)
    xy = jnp.stack([jnp.cos(t), jnp.sin(t)], 1)
    f = jax.jit(lambda xy: R.from_samples(t, xy, min_speed=0.5).position(jnp.asarray(1.0)))
    with pytest.warns(UserWarning, match="min_speed = 0.5 m/s is not checked on traced samples"):
        got = f(xy)
    np.testing.assert_allclose(
        np.asarray(got), np.asarray(R.from_samples(t, xy).position(jnp.asarray(1.0))), rtol=1e-13
    )


def _dense_solve(values, starts, rhs, block):
    """The collocation system solved dense (what the spline did before the banded solve)."""
    n, w = values.shape
    A = jnp.zeros((n, n), values.dtype).at[jnp.arange(n)[:, None], starts[:, None] + jnp.arange(w)].set(values)
    return jnp.linalg.solve(A, rhs)


@pytest.mark.parametrize("degree", [5, 7])
def test_a_long_uneven_path_is_scipys_spline(degree, monkeypatch):
    """1500 unevenly spaced samples (5 to 20 ms): the banded solve gives SciPy's
    make_interp_spline (not-a-knot for 5, natural ends for 7) as closely as the dense solve of the
    same system did, derivative by derivative (the high ones are ill-conditioned at this spacing,
    for SciPy as for us: 6e-5 of the scale for the fourth of degree 5, measured)."""
    rng = np.random.default_rng(3)
    t = np.cumsum(rng.uniform(0.005, 0.02, 1500))
    xy = np.c_[np.cos(0.7 * t) * t, np.sin(0.4 * t)]
    bc = None if degree == 5 else ([(4, np.zeros(2)), (5, np.zeros(2)), (6, np.zeros(2))],) * 2
    sp = make_interp_spline(t, xy, k=degree, bc_type=bc)
    ts = jnp.asarray(np.linspace(t[0], t[-1], 997))

    def jets():
        ref = R.from_samples(t, xy, degree=degree)
        return np.asarray(jax.jit(jax.vmap(lambda s: R.taylor(ref.position, s, degree - 1)))(ts))

    banded = jets()
    monkeypatch.setattr(R._math, "banded_solve", _dense_solve)
    jax.clear_caches()  # the spline's program is traced again, with the dense solve
    dense = jets()
    monkeypatch.undo()
    jax.clear_caches()  # and the dense one is not left in the cache for the tests after this one
    for d in range(degree):
        want = sp(np.asarray(ts), nu=d)
        scale = max(np.abs(want).max(), 1.0)
        err_band, err_dense = np.abs(banded[:, d] - want).max(), np.abs(dense[:, d] - want).max()
        assert err_band <= 3.0 * err_dense + 1e-12 * scale, (d, err_band, err_dense)
        if d <= 1:
            assert err_band < 1e-9 * scale, (d, err_band)
