"""Nothing silent: crossings of the singular set between samples, steps outside RK4's
stability region, inaccurate steps, references that stop or kink, certificates on coarse
grids, mismatched objects, corrupt checkpoints and file modes (the regression cases of
the reliability probe; the property-based bad-input suite is tests/test_bad_inputs.py)."""

import json
import os
import stat

import jax
import jax.numpy as jnp
import numpy as np
import pytest
import refpaths
from scipy.linalg import expm

import wmrjax as w
from wmrjax import _files as files
from wmrjax import certify as C
from wmrjax import references as R
from wmrjax.controllers import law


def _crossing_state(ctrl, params, t_cross):
    """An initial state whose exact error dynamics bring the velocity of P to zero at
    ``t_cross``: chi1 passes through zero there, linearly, between two samples."""
    A = np.asarray(ctrl.error_matrix(params.gains))
    jet = np.asarray(ctrl.reference_jet(t_cross, params))
    E = expm(A * t_cross)[2:4]  # velocity error rows of exp(A t)
    x0 = np.linalg.lstsq(E, -jet[1], rcond=None)[0]  # velocity error cancels the reference's at t_cross
    zeta = np.asarray(ctrl.reference_jet(0.0, params))[:2] + x0.reshape(2, 2)
    return ctrl.initial_state(jnp.asarray(zeta), params)


@pytest.mark.parametrize("dt", [0.01, 0.02, 0.05, 0.1])
def test_crossing_between_samples_is_flagged(paper61, dt):
    ctrl, params, _ = paper61
    t_cross = 2.0 + dt / 3.0  # never on the sampling grid
    z0 = _crossing_state(ctrl, params, t_cross)
    floor = 1e-9
    tr = w.simulate(ctrl, z0, params, dt=dt, n_steps=int(round(10 / dt)), margin_floor=floor)
    d = tr.diagnostics
    assert bool(d.singular) and bool(d.failed) and not bool(d.nonfinite)
    # the sampled margin never reached the floor: only the sign change of det K (= chi1) tells
    assert float(d.min_margin) > 1e3 * floor
    assert t_cross - 0.1 <= float(d.t_failure) <= t_cross + dt
    valid = np.asarray(tr.valid)
    t = np.asarray(tr.t)
    assert valid[t < float(d.t_failure) - 1e-9].all() and not valid[t >= float(d.t_failure) - 1e-9].any()
    # the frozen state is the first sample on the other side: the branch has reversed there
    assert float(tr.final_state[3]) < 0 < float(z0[3])


def test_regular_run_has_no_crossing(paper61):
    ctrl, params, z0 = paper61
    d = w.simulate(ctrl, z0, params, dt=0.01, n_steps=1000).diagnostics
    assert not bool(d.failed) and not bool(d.singular) and not bool(d.inaccurate)
    assert float(d.error_estimate) < 1e-8


def test_error_estimate_is_third_order_and_matches_the_true_local_error(paper61):
    """h (k4 - k5) / 6 is the difference of RK4 and its embedded third-order solution: it
    scales like dt^4, and bounds RK4's own local error (against a fine reference)."""
    ctrl, params, z0 = paper61
    est = {}
    for dt in (0.02, 0.04):
        est[dt] = float(w.simulate(ctrl, z0, params, dt=dt, n_steps=int(round(2 / dt))).diagnostics.error_estimate)
    order = np.log2(est[0.04] / est[0.02])
    assert 3.5 < order < 4.6, order
    # one step from z0 with dt = 0.04, against 64 substeps
    one = w.simulate(ctrl, z0, params, dt=0.04, n_steps=1).final_state
    fine = w.simulate(ctrl, z0, params, dt=0.04 / 64, n_steps=64).final_state
    local = float(jnp.max(jnp.abs(one - fine) / (1 + jnp.abs(fine))))
    assert local <= 2 * est[0.04]


def test_inaccurate_step_is_flagged_with_a_user_tolerance(paper61):
    ctrl, params, z0 = paper61
    d = w.simulate(ctrl, z0, params, dt=1.0, n_steps=10).diagnostics  # default error_tol = 1e-3
    assert bool(d.inaccurate) and bool(d.failed) and float(d.error_estimate) > 1e-3
    np.testing.assert_allclose(float(d.t_failure), 1.0, atol=1e-12)  # the first step already: frozen there
    loose = w.simulate(ctrl, z0, params, dt=1.0, n_steps=10, error_tol=0.1).diagnostics
    assert not bool(loose.inaccurate) and not bool(loose.failed)
    np.testing.assert_allclose(float(loose.error_estimate), 0.017373646906762193, rtol=1e-6)
    ok = w.simulate(ctrl, z0, params, dt=0.5, n_steps=20).diagnostics  # 7.7e-4: accepted
    assert not bool(ok.failed)
    np.testing.assert_allclose(float(ok.error_estimate), 7.682745873583789e-4, rtol=1e-6)


def test_unstable_step_is_refused(paper61):
    ctrl, params, z0 = paper61
    with pytest.raises(ValueError, match=r"dt = 10 s is outside RK4's stability region.*dt <= 2\.785"):
        w.simulate(ctrl, z0, params, dt=10.0, n_steps=2)
    fast = params._replace(gains=w.Gains.from_poles(10.0, 2, 2))
    with pytest.raises(ValueError, match=r"pole at -10.*dt <= 0\.2785"):
        w.simulate(ctrl, z0, fast, dt=0.3, n_steps=2)


def test_rk4_stability_boundary():
    # on the negative real axis RK4 is stable up to |dt lambda| = 2.7853
    np.testing.assert_allclose(law.rk4_max_step(np.array([-1.0])), 2.785293563, rtol=1e-8)
    np.testing.assert_allclose(law.rk4_amplification(-2.785293563), 1.0, atol=1e-8)
    # on the imaginary axis up to 2 sqrt(2)
    np.testing.assert_allclose(law.rk4_max_step(np.array([1j, -1j])), 2 * np.sqrt(2), rtol=1e-8)


def test_mismatched_parameters_are_refused(paper61):
    ctrl, params, z0 = paper61
    d11 = w.dynamic_linearization("(1,1)")
    p11 = d11.params(R.circle(), poles=1.0, geometry=w.Geometry(L=1.0, e=0.3))
    with pytest.raises(ValueError, match=r"gains.coeffs must have shape \(2, 2\).*got \(2, 3\)"):
        w.simulate(ctrl, z0, p11, dt=0.01, n_steps=10)
    # complex coefficients: a raw TypeError from inside the law before (the probe of #34)
    cx = w.Gains(jnp.asarray([[1.0 + 0.5j, 2.0], [1.0, 2.0]]))
    with pytest.raises(ValueError, match="gains.coeffs must be real.*complex128.*Gains.from_damping"):
        ctrl.params(R.paper_62(), gains=cx, geometry=w.Geometry(e=0.0))
    stat20 = w.static_linearization("(2,0)")
    sp = stat20.params(R.circle(), geometry=w.Geometry(e=0.3, delta=np.pi / 2))
    with pytest.raises(ValueError, match="params must be the DynamicParams"):
        w.simulate(ctrl, z0, sp, dt=0.01, n_steps=10)
    with pytest.raises(ValueError, match="params must be the StaticParams"):
        w.simulate(stat20, jnp.zeros(3), params, dt=0.01, n_steps=10)


def test_simulation_scalars_are_checked(paper61):
    ctrl, params, z0 = paper61
    for kw, msg in (
        (dict(t0=np.nan), "t0 must be a finite real scalar"),
        (dict(margin_floor=np.nan), "margin_floor must be a finite real scalar >= 0"),
        (dict(margin_floor=-1.0), "margin_floor must be"),
        (dict(error_tol=0.0), "error_tol must be a real scalar > 0"),
        (dict(dt=1j), "dt must be a finite real scalar"),
    ):
        with pytest.raises(ValueError, match=msg):
            w.simulate(ctrl, z0, params, **({"dt": 0.01, "n_steps": 10} | kw))
    with pytest.raises(ValueError, match="z0 must be real, got a complex state"):
        w.simulate(ctrl, z0.astype(jnp.complex128), params, dt=0.01, n_steps=10)
    with pytest.raises(ValueError, match=r"n_steps = 100000000000 .* needs about .* GB .* of memory available now"):
        w.simulate(ctrl, z0, params, dt=1e-10, n_steps=10**11)


def test_float32_state_is_promoted(paper61):
    ctrl, params, z0 = paper61
    a = w.simulate(ctrl, z0.astype(jnp.float32), params, dt=0.01, n_steps=20).final_state
    b = w.simulate(ctrl, z0.astype(jnp.float32).astype(jnp.float64), params, dt=0.01, n_steps=20).final_state
    assert a.dtype == jnp.float64
    np.testing.assert_array_equal(np.asarray(a), np.asarray(b))


# --- references -----------------------------------------------------------------------------


@pytest.fixture(scope="module")
def ctrl61():
    return w.dynamic_linearization("(2,0)")


def test_reference_stop_is_caught_on_any_horizon(ctrl61):
    p66 = ctrl61.params(R.paper_66(), poles=1.0, geometry=w.Geometry(e=0.0))
    ctrl61.check_reference(p66, 9.9)
    for t_final in (10.0, 12.0, 15.0, 60.0):
        with pytest.raises(ValueError, match=r"reaches the singular set .* at t = (9\.99|10)"):
            ctrl61.check_reference(p66, t_final)
    z0 = ctrl61.reference_state(0.0, p66)
    with pytest.raises(ValueError, match="reaches the singular set"):  # simulate checks its own horizon
        w.simulate(ctrl61, z0, p66, dt=0.01, n_steps=1500)


@pytest.mark.parametrize("path, order, where", [(refpaths.kink, 1, "2"), (refpaths.accel_kink, 2, "2.5")])
def test_reference_kink_is_caught(ctrl61, path, order, where):
    ref = R.from_function(path, name="kinked")
    params = ctrl61.params(ref, poles=1.0, geometry=w.Geometry(e=0.0))
    ctrl61.check_reference(params, 1.9)  # smooth before the kink
    with pytest.raises(ValueError, match=rf"derivative of order {order} jumps between t = .* and {where} s"):
        ctrl61.check_reference(params, 5.0)
    z0 = ctrl61.reference_state(0.0, params)
    with pytest.raises(ValueError, match="not smooth enough"):
        w.simulate(ctrl61, z0, params, dt=0.01, n_steps=500)


def test_kink_check_accepts_smooth_references_and_angle_wraps():
    d21 = w.dynamic_linearization("(2,1)")
    g = d21.row.default_geometry
    for ref in (R.circle(radius=1.0, omega=2.0, heading_offset=0.3), R.figure_eight(heading_offset=0.3), R.paper_62()):
        d21.check_reference(d21.params(ref, poles=1.0, geometry=g), 30.0)  # theta wraps past +-pi on the circle


def test_stopped_or_malformed_references_are_refused(ctrl61):
    g = w.Geometry(e=0.0)
    with pytest.raises(ValueError, match="is at rest at t = 0"):
        ctrl61.params(R.line(velocity=(0.0, 0.0)), poles=1.0, geometry=g)
    with pytest.raises(ValueError, match=r"must return the position \(x, y\) of shape \(2,\).*got \(3,\)"):
        ctrl61.params(R.from_function(refpaths.three), poles=1.0, geometry=g)
    with pytest.raises(ValueError, match="cannot be traced by JAX"):
        ctrl61.params(R.from_function(refpaths.numpy_path), poles=1.0, geometry=g)
    with pytest.raises(ValueError, match=r"must return the position"):
        w.static_linearization("(3,0)").params(R.from_function(refpaths.three))


# --- certificates ---------------------------------------------------------------------------


def test_lemma2_refuses_coarse_grids_and_unknown_options(paper61):
    ctrl, params, _ = paper61
    for n_t in (0, 1, 2):
        with pytest.raises(ValueError, match="n_t must be an integer >= 3"):
            C.lemma2(ctrl, params, t_final=10.0, eps=0.01, n_t=n_t)
    # n_t = 3: min F on the grid is 0.8868, 15 % above the true 0.76818: refused
    with pytest.raises(ValueError, match=r"n_t = 3 is too coarse to bound min F.*0\.886827 on the grid"):
        C.lemma2(ctrl, params, t_final=10.0, eps=0.01, n_t=3)
    fine = C.lemma2(ctrl, params, t_final=10.0, eps=0.01, n_t=1001)  # equal to n_t = 4001's within 2e-10
    for n_t in (11, 101):
        # a grid minimum alone over-certifies (0.768599 at n_t = 11, and the exact-norm radius by
        # 1.4e-4 relative at n_t = 101); the refinement between points brings every radius to the
        # fine grid's within 2e-5 relative
        rep = C.lemma2(ctrl, params, t_final=10.0, eps=0.01, n_t=n_t)
        for name in ("paper", "lyapunov", "exact_norm"):
            a, b = float(getattr(rep, name).radius), float(getattr(fine, name).radius)
            assert abs(a - b) <= 2e-5 * b, (n_t, name, a, b)
    np.testing.assert_allclose(float(fine.paper.radius), 0.7681795, atol=1e-7)
    for bad in ("closedform", "Closed", 1, None):
        with pytest.raises(ValueError, match="m1 must be one of"):
            C.lemma2(ctrl, params, t_final=10.0, eps=0.01, m1=bad)


# --- files ---------------------------------------------------------------------------------


def test_output_files_follow_the_umask(tmp_path):
    old = os.umask(0o022)
    try:
        files.write_json(tmp_path / "a.json", {"x": 1})
        files.write_npz(tmp_path / "b.npz", x=np.zeros(2))
    finally:
        os.umask(old)
    for f in ("a.json", "b.npz"):
        assert stat.S_IMODE(os.stat(tmp_path / f).st_mode) == 0o644


@pytest.mark.parametrize(
    "content, msg",
    [
        ("", "corrupt or truncated"),
        ('{"fingerprint": "abc", "step": 3, "trees": {"raw": [[1.0, 2.0', "corrupt or truncated"),
        ("[1, 2, 3]", "is not a checkpoint"),
        ("\udcff", "corrupt or truncated"),
    ],
)
def test_corrupt_checkpoint_names_the_file(tmp_path, content, msg):
    path = tmp_path / "checkpoint.json"
    path.write_text(content, errors="surrogateescape")
    with pytest.raises(ValueError, match=msg) as exc:
        files.read_checkpoint(path, fingerprint="abc", config={}, templates={"raw": jnp.zeros(2)})
    assert str(path) in str(exc.value)


def test_edited_checkpoint_is_refused(tmp_path):
    path = tmp_path / "checkpoint.json"
    files.write_checkpoint(path, fingerprint="abc", config={}, step=3, trees={"raw": jnp.zeros(2)}, state={"a": 1})
    good = json.loads(path.read_text())
    for edit, msg in (
        (lambda d: d["trees"]["raw"][0].pop(), r"has shape \(1,\), expected \(2,\)"),
        (lambda d: d["trees"]["raw"].__setitem__(0, ["a", "b"]), "not a numeric array"),
        (lambda d: d["trees"]["raw"].__setitem__(0, [[1.0], 2.0]), "not a numeric array"),
        (lambda d: d["trees"].pop("raw"), "has None leaves"),
        (lambda d: d.pop("step"), "lacks an integer 'step'"),
    ):
        d = json.loads(json.dumps(good))
        edit(d)
        path.write_text(json.dumps(d))
        with pytest.raises(ValueError, match=msg):
            files.read_checkpoint(path, fingerprint="abc", config={}, templates={"raw": jnp.zeros(2)})


def test_hybrid_checks_its_parameters(paper61):
    ctrl, params, _ = paper61
    hy = w.hybrid_parking()
    hp = hy.params(R.paper_66())
    z0 = hy.initial_state(jnp.array([[2.357, 2.54], [-0.5, -0.5]]), hp)
    with pytest.raises(ValueError, match="params must be HybridParams"):
        w.simulate(hy, z0, params, dt=0.01, n_steps=10)
    with pytest.raises(ValueError, match="outside RK4's stability region"):
        w.simulate(hy, z0, hp, dt=5.0, n_steps=2)
    jax.block_until_ready(w.simulate(hy, z0, hp, dt=0.01, n_steps=10).final_state)


def test_heartbeat_reports_a_silent_stage():
    import io as _io
    import time

    from wmrjax.cli import running

    buf = _io.StringIO()
    with running.Heartbeat(every=0.05, stream=buf) as hb:
        hb.stage("compiling the rollout")
        time.sleep(0.6)
        hb.stage("writing figures")
    lines = buf.getvalue().splitlines()
    assert lines[0].endswith("compiling the rollout") and lines[-1].endswith("writing figures")
    assert sum("still working (last: compiling the rollout)" in x for x in lines) >= 2


def test_error_estimate_can_be_compiled_out(paper61):
    """error_tol=None: the same states, no estimate (what the benchmark's bare row measures)."""
    ctrl, params, z0 = paper61
    a = w.simulate(ctrl, z0, params, dt=0.01, n_steps=200)
    b = w.simulate(ctrl, z0, params, dt=0.01, n_steps=200, error_tol=None)
    np.testing.assert_array_equal(np.asarray(a.state), np.asarray(b.state))
    assert float(b.diagnostics.error_estimate) == 0.0 and float(a.diagnostics.error_estimate) > 0.0
    assert not bool(b.diagnostics.inaccurate)


def test_kink_in_the_middle_of_a_grid_interval_is_caught_and_named(ctrl61):
    """A jump halfway between two grid points leaves no trapezoid residual on that grid: the check
    also runs on the midpoints' grid, and names the order that jumps."""
    for path, order in ((refpaths.velocity_kink_midway, 1), (refpaths.accel_kink_midway, 2)):
        params = ctrl61.params(R.from_function(path), poles=1.0, geometry=w.Geometry(e=0.0))
        with pytest.raises(ValueError, match=rf"derivative of order {order} jumps"):
            ctrl61.check_reference(params, 10.0)


def test_reference_checked_under_an_outer_jit(ctrl61):
    params = ctrl61.params(R.from_function(refpaths.kink), poles=1.0, geometry=w.Geometry(e=0.0))
    z0 = ctrl61.reference_state(0.0, params)
    with pytest.raises(ValueError, match="not smooth enough"):
        jax.jit(lambda z: w.simulate(ctrl61, z, params, dt=0.01, n_steps=500).final_state)(z0)


def test_check_reference_with_a_traced_horizon_says_it_checked_nothing(ctrl61):
    """It returned without a word (the probe's check-reference-traced-horizon): a user who calls
    it under jit believes the reference was checked."""
    p66 = ctrl61.params(R.paper_66(), poles=1.0, geometry=w.Geometry(e=0.0))  # stops at t = 10 s
    with pytest.warns(UserWarning, match=r"t_final is traced .* not checked"):
        jax.jit(lambda T: ctrl61.check_reference(p66, T))(15.0)
    import warnings

    with warnings.catch_warnings():  # simulate under jit checks with its concrete horizon, silently
        warnings.simplefilter("error")
        z0 = ctrl61.reference_state(0.0, p66)
        jax.jit(lambda z: w.simulate(ctrl61, z, p66, dt=0.01, n_steps=50).final_state)(z0)


def test_reference_errors_batch_gives_check_references_verdicts(ctrl61, monkeypatch):
    """reference_errors (a problem's references checked together) gives check_reference's verdict
    and message for each parameter set: paths sampled at the same times stack into one batched
    program (the one-at-a-time program is never called), a set that does not stack (another
    family) is checked on its own."""
    from wmrjax.controllers import law

    g = w.Geometry(e=0.0)
    t = np.linspace(0.0, 12.0, 121)
    sources = (R.circle(radius=2.0, omega=0.4), R.paper_66(), R.figure_eight())  # paper_66 stops at t = 10 s
    params = [
        ctrl61.params(R.from_samples(t, np.asarray(jax.vmap(r.position)(t))), geometry=g, poles=1.0) for r in sources
    ]
    expected = []
    for p in params:
        try:
            ctrl61.check_reference(p, 11.0)
            expected.append(None)
        except ValueError as err:
            expected.append(str(err))
    assert expected[0] is None and expected[2] is None and "reaches the singular set" in expected[1]

    def one_at_a_time(*args, **kwargs):
        raise AssertionError("stacked references are checked by the batched program")

    with monkeypatch.context() as m:
        m.setattr(law, "reference_profile", one_at_a_time)
        assert ctrl61.reference_errors(params, 11.0) == expected
    mixed = [ctrl61.params(R.circle(radius=2.0, omega=0.4), poles=1.0, geometry=g), params[1]]
    assert ctrl61.reference_errors(mixed, 11.0) == [None, expected[1]]
    assert ctrl61.reference_errors([], 11.0) == []
