"""Simulator and the (2,0) dynamic linearizing closed loop (§6.1)."""

import dataclasses
import os
import pathlib
import re
import subprocess
import sys
import textwrap
import warnings

import jax
import jax.numpy as jnp
import numpy as np
import pytest
from scipy.integrate import solve_ivp
from scipy.linalg import expm

import wmrjax as w
from benchmarks.benchmark import numpy_rollout_rhs
from wmrjax import references as R
from wmrjax.controllers.law import Aux


def numpy_closed_loop(t, s):
    """§6.1 closed loop written by hand from eq (39) in NumPy (independent of the engine);
    the same law the benchmark's NumPy baseline runs."""
    return np.array(numpy_rollout_rhs(t, s))


@pytest.fixture(scope="module")
def run61(paper61):
    ctrl, params, z0 = paper61
    return w.simulate(ctrl, z0, params, dt=0.01, n_steps=1000)


def test_vector_field_matches_hand_written_law(paper61, rng):
    ctrl, params, _ = paper61
    for _ in range(10):
        t = rng.uniform(0, 10)
        s = np.array([*rng.uniform(3, 7, 2), rng.uniform(-3, 3), rng.uniform(0.5, 5)])
        zdot, aux = ctrl.vector_field(jnp.asarray(t), jnp.asarray(s), params)
        np.testing.assert_allclose(zdot, numpy_closed_loop(t, s), rtol=1e-11, atol=1e-11)
        np.testing.assert_allclose(aux.margin, abs(s[3]), rtol=1e-13)
        np.testing.assert_allclose(aux.control, [s[3], numpy_closed_loop(t, s)[2]], rtol=1e-11)  # (eta1, eta2), e = 0


def test_rk4_is_fourth_order_against_dop853(paper61):
    ctrl, params, z0 = paper61
    T = 2.0
    ref = solve_ivp(numpy_closed_loop, (0, T), np.asarray(z0), method="DOP853", rtol=1e-11, atol=1e-12).y[:, -1]
    errs = []
    for n in (25, 50, 100):
        tr = w.simulate(ctrl, z0, params, dt=T / n, n_steps=n, save_every=n)
        errs.append(np.max(np.abs(np.asarray(tr.final_state) - ref)))
    orders = np.log2(np.array(errs[:-1]) / np.array(errs[1:]))
    assert np.all((orders > 3.7) & (orders < 4.4)), (errs, orders)
    assert errs[-1] < 1e-7


def test_error_follows_exact_linear_dynamics(paper61, run61):
    """e'' + 2 e' + e = 0 per axis: the simulated error equals expm(A t) err(0)."""
    ctrl, params, _ = paper61
    err = jax.vmap(lambda t, z: ctrl.error(t, z, params))(run61.t, run61.state).reshape(len(run61.t), -1)
    A = np.asarray(ctrl.error_matrix(params.gains))
    exact = np.stack([expm(A * t) @ np.asarray(err[0]) for t in np.asarray(run61.t)])
    resid = np.max(np.abs(np.asarray(err) - exact))
    assert resid < 1e-8, resid
    assert np.max(np.abs(err[0])) > 0.5  # a real initial error (0.54 m per axis)
    assert np.max(np.abs(err[-1])) < 1e-3  # converged (e^{-t}(1 + t) at 10 s ~ 5e-4)


def test_nonholonomic_constraint_along_run(run61):
    """Type (2,0): no sideways motion of P, xdot cos(theta) + ydot sin(theta) = 0."""
    s = np.asarray(run61.state)
    dt = float(run61.t[1] - run61.t[0])
    xd = (s[2:, 0] - s[:-2, 0]) / (2 * dt)
    yd = (s[2:, 1] - s[:-2, 1]) / (2 * dt)
    th = s[1:-1, 2]
    lateral = xd * np.cos(th) + yd * np.sin(th)
    speed = np.hypot(xd, yd)
    assert np.max(np.abs(lateral)) < 1e-3 * np.max(speed)
    assert np.max(speed) > 1.0


def test_run61_diagnostics(run61):
    d = run61.diagnostics
    assert not bool(d.failed) and not bool(d.nonfinite) and not bool(d.singular)
    assert bool(jnp.all(run61.valid))
    np.testing.assert_allclose(float(d.min_margin), 1.0003309108119178, rtol=1e-12)  # min chi1, at t = 5 s (eq 65)
    np.testing.assert_allclose(float(d.t_min_margin), 5.0, atol=1e-12)
    assert run61.state.shape == (1001, 4) and run61.control.shape == (1001, 2)


def test_vmap_equals_python_loop_and_jit_equals_nojit(paper61):
    ctrl, params, z0 = paper61
    z0s = jnp.stack([z0 + jnp.array([0.1 * i, -0.05 * i, 0.0, 0.0]) for i in range(3)])
    sim = lambda z: w.simulate(ctrl, z, params, dt=0.02, n_steps=4, save_every=2)
    batched = jax.jit(jax.vmap(sim))(z0s)
    for i in range(3):
        single = sim(z0s[i])
        np.testing.assert_allclose(batched.state[i], single.state, rtol=1e-13, atol=1e-13)
    with jax.disable_jit():  # op by op, no XLA fusion: same numbers to rounding
        nojit = sim(z0s[1])
    np.testing.assert_allclose(nojit.state, batched.state[1], rtol=1e-12, atol=1e-12)
    np.testing.assert_allclose(nojit.control, batched.control[1], rtol=1e-11, atol=1e-11)


@dataclasses.dataclass(frozen=True)
class _CountingLoop(w.ClosedLoop):
    """The §6.1 closed loop, counting how often its vector field is traced (a test's counter)."""

    ctrl: object
    calls: list = dataclasses.field(default_factory=list, compare=False, hash=False)

    @property
    def n_state(self):
        return self.ctrl.n_state

    @property
    def state_names(self):
        return self.ctrl.state_names

    def vector_field(self, t, z, params):
        self.calls.append(1)
        return self.ctrl.vector_field(t, z, params)


def test_inside_an_outer_trace_simulate_traces_the_law_once_and_adds_no_call(paper61):
    """Called inside jit (vmap, grad), simulate traces into the outer program: no jitted call of its
    own for the outer transformations to process again, and the law traced once per run (the
    loop's scalar field serves the initial shapes and the final state's evaluation too). Same
    numbers as the jitted entry point called with concrete arguments."""
    ctrl, params, z0 = paper61
    loop = _CountingLoop(ctrl)
    sim = lambda z: w.simulate(loop, z, params, dt=0.02, n_steps=6, save_every=3)
    jaxpr = jax.make_jaxpr(sim)(z0)
    assert len(loop.calls) == 1
    names = [e.params.get("name") for e in jaxpr.jaxpr.eqns if e.primitive.name in ("jit", "pjit")]
    assert "_simulate" not in names
    inner, outer = jax.jit(sim)(z0), sim(z0)  # traced into jit / the jitted entry point
    np.testing.assert_array_equal(inner.state, outer.state)
    np.testing.assert_array_equal(inner.margin, outer.margin)


def test_vmap_over_references_and_gains(paper61):
    ctrl, params, z0 = paper61
    poles = jnp.array([1.0, 2.0])
    batched = jax.vmap(
        lambda p: (
            w.simulate(
                ctrl,
                z0,
                params._replace(gains=w.Gains.from_poles(jnp.full((2, 2), p))),
                dt=0.02,
                n_steps=50,
                save_every=50,
            ).final_state
        )
    )(poles)
    for i, p in enumerate([1.0, 2.0]):
        one = w.simulate(
            ctrl,
            z0,
            ctrl.params(params.reference, poles=p, geometry=params.geometry),
            dt=0.02,
            n_steps=50,
            save_every=50,
        ).final_state
        assert float(jnp.abs(one - z0).max()) > 0.1
        np.testing.assert_allclose(batched[i], one, rtol=1e-13)


def test_batch_map_equals_vmap(paper61):
    ctrl, params, z0 = paper61
    z0s = z0 + jnp.linspace(-0.2, 0.2, 7)[:, None] * jnp.array([1.0, 1.0, 0.0, 0.0])
    sim = lambda z: w.simulate(ctrl, z, params, dt=0.05, n_steps=20, save_every=20).final_state
    a = jax.jit(jax.vmap(sim))(z0s)
    b = jax.jit(lambda z: w.batch_map(sim, z, chunk=3))(z0s)  # 7 -> padded to 9, 3 chunks
    np.testing.assert_allclose(a, b, rtol=1e-14)


def test_several_devices_agree_with_one():
    """batch_map and sharded vmap on 4 forced host devices equal the single-device run."""
    code = textwrap.dedent("""
        import jax, jax.numpy as jnp, numpy as np
        jax.config.update("jax_enable_x64", True)
        import wmrjax as w
        from wmrjax import references as R
        assert len(jax.devices()) == 4
        c = w.dynamic_linearization("(2,0)")
        p = c.params(R.paper_62(), poles=1.0)
        z0 = c.reference_state(0.0, p)
        z0s = z0 + jnp.linspace(-0.3, 0.3, 10)[:, None] * jnp.array([1.0, -1.0, 0.0, 0.0])
        sim = lambda z: w.simulate(c, z, p, dt=0.05, n_steps=20, save_every=20).final_state
        a = jax.jit(lambda z: w.batch_map(sim, z, chunk=2))(z0s)
        b = jax.jit(jax.vmap(sim))(w.shard_batch(z0s[:8]))
        np.save("out.npy", np.concatenate([np.asarray(a), np.asarray(b)]))
    """)
    import tempfile

    with tempfile.TemporaryDirectory() as tmp:
        env = dict(os.environ, XLA_FLAGS="--xla_force_host_platform_device_count=4", JAX_PLATFORMS="cpu")
        root = os.path.dirname(os.path.dirname(os.path.abspath(__file__)))
        env["PYTHONPATH"] = root + os.pathsep + env.get("PYTHONPATH", "")
        subprocess.run([sys.executable, "-c", code], cwd=tmp, env=env, check=True, timeout=300)
        multi = np.load(os.path.join(tmp, "out.npy"))
    c = w.dynamic_linearization("(2,0)")
    p = c.params(R.paper_62(), poles=1.0)
    z0 = c.reference_state(0.0, p)
    z0s = z0 + jnp.linspace(-0.3, 0.3, 10)[:, None] * jnp.array([1.0, -1.0, 0.0, 0.0])
    single = jax.vmap(lambda z: w.simulate(c, z, p, dt=0.05, n_steps=20, save_every=20).final_state)(z0s)
    np.testing.assert_allclose(multi[:10], single, rtol=1e-14)
    np.testing.assert_allclose(multi[10:], single[:8], rtol=1e-14)


def test_on_reference_stays_on_reference(paper61):
    """Property 3 of §3.1: started on the reference (with matching chi1) it stays there."""
    ctrl, params, _ = paper61
    zref0 = ctrl.reference_state(0.0, params)
    tr = w.simulate(ctrl, zref0, params, dt=0.01, n_steps=500, save_every=50)
    for t, z in zip(tr.t, tr.state):
        np.testing.assert_allclose(z, ctrl.reference_state(float(t), params), atol=1e-9)


# --- failure handling -------------------------------------------------------------


@dataclasses.dataclass(frozen=True)
class _Falling(w.ClosedLoop):
    """z' = -1 from z = 1: margin |z| hits zero at t = 1; control log(z) is NaN after."""

    n_state: int = 1

    def vector_field(self, t, z, params):
        return -jnp.ones_like(z), Aux(jnp.log(z), jnp.abs(z[0]))


def test_singular_run_is_flagged_and_frozen():
    tr = w.simulate(_Falling(), jnp.array([1.0]), (), dt=0.1, n_steps=20, margin_floor=0.25)
    d = tr.diagnostics
    assert bool(d.singular) and bool(d.failed) and not bool(d.nonfinite)
    np.testing.assert_allclose(d.t_failure, 0.8, atol=1e-12)  # z(0.7) = 0.3 > 0.25, z(0.8) = 0.2
    valid = np.asarray(tr.valid)
    assert valid[:8].all() and not valid[8:].any()
    np.testing.assert_allclose(d.min_margin, 0.3, atol=1e-12)
    assert np.all(np.isfinite(np.asarray(tr.state)))
    assert float(tr.final_state[0]) > 0.2  # frozen, never ran past the singularity


def test_nonfinite_run_is_flagged():
    tr = w.simulate(_Falling(), jnp.array([1.0]), (), dt=0.1, n_steps=20, margin_floor=0.0)
    d = tr.diagnostics
    assert bool(d.nonfinite) and bool(d.failed)
    assert np.all(np.isfinite(np.asarray(tr.state)))
    assert not bool(tr.valid[-1])


@dataclasses.dataclass(frozen=True)
class _Overflowing(w.ClosedLoop):
    """x' = 0 except at t = 0.5, where x' = +M below x = 1 and -M above, M near the float max.

    With dt = 0.125 the step ending at t = 0.5 has stages 0, 0, 0, +M: it lands at dt M / 6
    (finite), where the next step's stages are -M, 0, 0, 0, so the error estimate's difference
    k4 - k5 = 2M overflows: the estimate is inf while the state, the control and the margin stay
    finite (the next state too: back to 0)."""

    n_state: int = 1

    def vector_field(self, t, z, params):
        big = 0.9 * np.finfo(np.float64).max
        dz = jnp.where(t == 0.5, jnp.where(z < 1.0, big, -big), 0.0)
        return dz, Aux(jnp.zeros(1) + 1.0, jnp.array(1.0))


@pytest.mark.parametrize("n_steps", [4, 8])
def test_nonfinite_error_estimate_fails_the_run_in_the_step_and_at_the_end(n_steps):
    """One failure rule at every step and at the final state: a run ending right after the step
    whose estimate overflows (judged at the final state) and one going on (judged in the step)
    both fail there as non-finite (the step used to fail it with no cause flagged, not non-finite,
    while the final state marked it non-finite)."""
    tr = w.simulate(_Overflowing(), jnp.array([0.0]), (), dt=0.125, n_steps=n_steps)
    d = tr.diagnostics
    assert np.all(np.isfinite(np.asarray(tr.state))) and np.all(np.isfinite(np.asarray(tr.control)))
    assert bool(d.failed) and bool(d.nonfinite) and not bool(d.singular) and not bool(d.inaccurate)
    assert float(d.t_failure) == 0.5 and float(d.error_estimate) == 0.0
    assert np.asarray(tr.valid).tolist() == [True] * 4 + [False] * (n_steps - 3)
    np.testing.assert_allclose(tr.final_state, [0.125 / 6 * 0.9 * np.finfo(np.float64).max])


def test_traced_bad_dt_fails_the_run_at_t0(paper61):
    """Under jit and vmap dt cannot be refused before compiling: a dt <= 0 or NaN fails every run
    at t0 (no sample valid, the state frozen at z0) instead of integrating backwards (it gave
    t[-1] = -1 s and failed = False)."""
    ctrl, params, z0 = paper61
    run = jax.jit(lambda dt: w.simulate(ctrl, z0, params, dt=dt, n_steps=100, save_every=10))
    assert not bool(run(0.01).diagnostics.failed)
    for dt in (-0.01, 0.0, np.nan, np.inf):
        tr = run(dt)
        d = tr.diagnostics
        assert bool(d.failed) and not bool(d.nonfinite) and not bool(d.singular) and float(d.t_failure) == 0.0
        assert not np.asarray(tr.valid).any()
        np.testing.assert_array_equal(tr.final_state, z0)
    batch = jax.vmap(lambda dt: w.simulate(ctrl, z0, params, dt=dt, n_steps=100))(jnp.array([0.01, -0.01]))
    assert np.asarray(batch.diagnostics.failed).tolist() == [False, True]


# --- bad input --------------------------------------------------------------------


def test_bad_simulate_arguments(paper61):
    ctrl, params, z0 = paper61
    with pytest.raises(ValueError, match="n_steps must be an integer >= 1"):
        w.simulate(ctrl, z0, params, dt=0.01, n_steps=0)
    with pytest.raises(ValueError, match="dt must be a finite real scalar > 0"):
        w.simulate(ctrl, z0, params, dt=-0.01, n_steps=10)
    with pytest.raises(ValueError, match=r"z0 must be an unbatched state of shape \(4,\)"):
        w.simulate(ctrl, jnp.zeros((2, 4)), params, dt=0.01, n_steps=10)
    with pytest.raises(ValueError, match=r"x, y, theta, chi1"):
        w.simulate(ctrl, jnp.zeros(3), params, dt=0.01, n_steps=10)
    with pytest.raises(ValueError, match="z0 must be finite"):
        w.simulate(ctrl, z0.at[0].set(jnp.nan), params, dt=0.01, n_steps=10)
    with pytest.raises(ValueError, match="save_every must be <= n_steps"):
        w.simulate(ctrl, z0, params, dt=0.01, n_steps=10, save_every=11)


def test_bad_controller_arguments(paper61):
    ctrl, params, z0 = paper61
    with pytest.raises(ValueError, match="on the singular set"):  # chi1 = 0: robot at rest
        ctrl.initial_state(jnp.array([[5.0, 6.0], [0.0, 0.0]]), params)
    with pytest.raises(ValueError, match="Remark 17"):
        ctrl.initial_state(jnp.array([[5.0, 6.0], [-3.5, -3.5]]), params, branch=-1)
    with pytest.raises(ValueError, match="zeta0 must have shape"):
        ctrl.initial_state(jnp.zeros(4), params)
    with pytest.raises(ValueError, match="zeta0 must be finite"):
        ctrl.initial_state(jnp.array([[5.0, jnp.inf], [-3.5, -3.5]]), params)
    with pytest.raises(ValueError, match="poles"):
        ctrl.params(params.reference, poles=-1.0)
    with pytest.raises(ValueError, match="poles"):
        ctrl.params(params.reference, poles=jnp.ones((3, 2)))
    with pytest.raises(ValueError, match="reference must be"):
        ctrl.params(lambda t: t, poles=1.0)
    with pytest.raises(ValueError, match="no dynamic extension"):
        w.dynamic_linearization("(3,0)")
    with pytest.raises(ValueError, match="level must be one of"):
        w.dynamic_linearization("(2,0)", level="acceleration")
    with pytest.raises(ValueError, match="geometry.L must be != 0"):
        w.dynamic_linearization("(1,1)").params(params.reference, geometry=w.Geometry(L=0.0))


def test_batch_map_chunks_for_cpu_caches_and_not_on_accelerators():
    """On a GPU, batch_value_and_grad's 256-example reverse chunks ran 65 536 examples as 256
    sequential programs: 518x the forward pass (docs/benchmarks.md, H100). The default chunk is
    now the CPU's cache-sized one on CPU devices only, one chunk per device elsewhere."""
    from types import SimpleNamespace

    from wmrjax.autodiff import BATCH_REVERSE_CHUNK
    from wmrjax.simulate import CPU_CHUNK, batch_mesh, default_chunk

    gpus = SimpleNamespace(devices=np.array([SimpleNamespace(platform="gpu")] * 2))
    assert default_chunk(gpus) is None and default_chunk(gpus, BATCH_REVERSE_CHUNK) is None
    assert default_chunk(batch_mesh()) == CPU_CHUNK == 512
    assert default_chunk(batch_mesh(), BATCH_REVERSE_CHUNK) == 256


def test_the_protocol_declares_every_hook_the_run_reads():
    """wmrjax.ClosedLoop declares every attribute of a system the run, the problem file and the
    memory model read (no getattr probe for an undeclared hook); an object that is not one is
    refused before anything compiles, naming the base to subclass."""
    read = set()
    for mod in ("simulate.py", "problem/setting.py", "resources.py"):
        text = (pathlib.Path(w.__file__).parent / mod).read_text()
        read |= set(re.findall(r"\bsystem\.([a-z_]+)\(?", text))
    assert {
        "vector_field",
        "post_step",
        "sample_every",
        "sample",
        "held",
        "final_report",
        "check_run",
        "law_state",
    } <= read
    assert read <= set(dir(w.ClosedLoop)), sorted(read - set(dir(w.ClosedLoop)))

    class Duck:  # the old duck-typed protocol: a vector field and nothing declared
        def vector_field(self, t, z, params):
            return -z, None

    with pytest.raises(ValueError, match="system must be a wmrjax.ClosedLoop"):
        w.simulate(Duck(), jnp.ones(1), None, dt=0.1, n_steps=2)


def test_a_long_float32_run_warns_and_a_float64_one_does_not(paper61):
    """x64 off is JAX's default: a long run's rounding then accumulates silently (the probe:
    six digits of tracking accuracy lost over a long horizon), so the run says so."""
    ctrl, params, z0 = paper61
    with jax.enable_x64(False):
        p32 = jax.tree_util.tree_map(lambda x: jnp.asarray(x, jnp.float32), params)
        with pytest.warns(RuntimeWarning, match="float32 .jax_enable_x64 is off. over 1000 steps"):
            tr = w.simulate(ctrl, jnp.asarray(z0, jnp.float32), p32, dt=0.01, n_steps=1000, save_every=1000)
        assert tr.state.dtype == jnp.float32
    with warnings.catch_warnings():
        warnings.simplefilter("error")
        w.simulate(ctrl, z0, params, dt=0.01, n_steps=1000, save_every=1000)
