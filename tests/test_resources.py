"""The checks that refuse oversized work before compiling, driven by the memory model; and the
measuring script of the model's calibration (``benchmarks.benchmark.memory_estimates``, run
at scale by ``python -m benchmarks.benchmark``) at a small size."""

import dataclasses
from pathlib import Path

import pytest

from benchmarks import benchmark as M
from wmrjax import resources

ROOT = Path(__file__).resolve().parents[1]


def test_the_measuring_script_runs_and_predicts_more_than_nothing():
    """At 20000 steps the growth is too small to hold the factor (the benchmark measures at 5e5
    and 2e6 steps); here the script runs and its prediction is the model's."""
    m = M.measure("simulate", 20_000, 0.02)
    assert m["predicted"] > 0 and m["measured"] >= 0


def test_oversized_work_is_refused_before_compiling(monkeypatch):
    import wmrjax as w
    from wmrjax import references as R

    monkeypatch.setattr(resources, "available_bytes", lambda: 2 * 10**9)
    ctrl = w.dynamic_linearization("(2,0)", "velocity")
    p = ctrl.params(R.paper_62(), poles=1.0)
    z0 = ctrl.initial_state(ctrl.reference_jet(0.0, p)[:2], p)
    # 1e7 steps of 0.01 s: 1.52 GB of samples and 3.6 GB of reference check (the old guard: 0.96 GB, accepted)
    with pytest.raises(ValueError, match=r"n_steps = 10000000 .* needs about 5.12 GB .* available now"):
        w.simulate(ctrl, z0, p, dt=0.01, n_steps=10**7)
    est = resources.run_estimate(ctrl, n_steps=10**7, save_every=1, n_state=4, itemsize=8, horizon=1e5)
    assert est.device == pytest.approx(1e7 * 19 * 8, rel=1e-6)


def test_oversized_tuning_and_sweeps_are_refused_before_compiling(monkeypatch):
    """wmrjax tune --set tune.scenarios.train=1000000 failed allocating 14.6 GB after 6 s; a sweep of 256
    runs of 400000 samples each asked for 8.3 GB per device with no estimate."""
    from wmrjax.problem import Problem
    from wmrjax.sweep import run as sweep_run
    from wmrjax.sweep import spec as S
    from wmrjax.tune import config, loop

    monkeypatch.setattr(resources, "available_bytes", lambda: 8 * 10**9)
    prob = Problem.load(ROOT / "wmrjax" / "examples" / "section_6_1_plant.toml")
    setting = prob.setting("tuning")
    sc = config.read(prob.section("tune")).scenarios
    loop.check_memory(setting, sc)
    with pytest.raises(
        ValueError,
        match=r"a gradient step over 1000000 training scenarios of 1000 steps needs about "
        r"130 GB .* lower the training scenarios \(\[tune.scenarios\] train\)",
    ):
        loop.check_memory(setting, sc._replace(train=10**6))
    # the probe's tuning-n-heldout-1e8: every scenario set is drawn at once (no estimate: the
    # process ran into the memory limit, its heartbeat printing "still working")
    with pytest.raises(
        ValueError,
        match=r"drawing 100000\d+ scenarios .* held-out 100000000\) .* \[tune.scenarios\] train, validation or heldout",
    ):
        loop.check_memory(setting, sc._replace(heldout=10**8))
    plan = S.load(M.SWEEP_FILE)
    sweep_run.check_memory(plan, 1)
    with pytest.raises(ValueError, match=r"2 process\(es\) x 2 device\(s\), each running a block of 256 runs"):
        sweep_run.check_memory(dataclasses.replace(plan, n_steps=400_000), 2, 2)


def test_a_reference_check_larger_than_memory_is_refused_before_it_starts(monkeypatch):
    """The probe's sweep-t-final-1e6: a problem over 1e6 s checked its reference on 2e8 grid points
    (36 GB) in 512-point blocks, with no estimate and no answer within minutes; the check now
    estimates itself first (the same model as simulate's) and evaluates nothing."""
    import wmrjax as w
    from wmrjax import references as R
    from wmrjax.controllers import law

    ctrl = w.dynamic_linearization("(2,0)", "velocity")
    p = ctrl.params(R.circle(radius=2.0, omega=0.5), poles=1.0)

    def no_work(*a, **k):
        raise AssertionError("the reference was evaluated before the estimate refused the check")

    monkeypatch.setattr(law, "reference_profile", no_work)
    monkeypatch.setattr(resources, "available_bytes", lambda: 24 * 10**9)
    expected = resources.check_bytes(1e6, 6) / 1e9  # (r + 1) m = 3 x 2 jet floats per grid point
    assert expected == pytest.approx(36.0, rel=0.01)
    with pytest.raises(ValueError, match=r"reference check over \[0, 1e\+06\] s .* needs about 36 GB"):
        ctrl.check_reference(p, 1e6)
    with pytest.raises(ValueError, match=r"needs about 36 GB"):
        w.simulate(ctrl, ctrl.reference_state(0.0, p), p, dt=0.02, n_steps=5 * 10**7, save_every=5 * 10**7)


def test_the_long_horizon_check_program_agrees_with_the_block_program(monkeypatch):
    """Grids above law.LONG_CHECK_POINTS are evaluated by an optimized program in larger blocks:
    the same jets, regularity and branch as the 512-point blocks (to rounding), and the same kink
    found on a path with a corner."""
    import numpy as np

    import wmrjax as w
    from wmrjax import references as R
    from wmrjax.controllers import law

    ctrl = w.dynamic_linearization("(2,0)", "velocity")
    p = ctrl.params(R.circle(radius=2.0, omega=0.5), poles=1.0)
    short = law.reference_profile(ctrl, p, 0.0, 12.0, 0.005)
    monkeypatch.setattr(law, "LONG_CHECK_POINTS", 1000)
    monkeypatch.setattr(law, "LONG_BLOCK", 1024)
    long = law.reference_profile(ctrl, p, 0.0, 12.0, 0.005)
    assert long[0].size == short[0].size == 2401
    for a, b in zip(short, long):
        np.testing.assert_allclose(b, a, rtol=1e-13, atol=1e-13)
    import refpaths

    pk = ctrl.params(R.from_function(refpaths.kink, name="kinked"), poles=1.0)  # its speed jumps at t = 2 s
    with pytest.raises(ValueError, match=r"order 1 jumps between t = .* and 2 s"):
        ctrl.check_reference(pk, 5.0)


def test_the_memory_available_respects_the_processes_own_limits():
    """A process under an address-space limit (``ulimit -v``, as a batch job or the probe runs it)
    took the machine's free memory for its own: a 1e8-run grid passed the estimate and failed with
    a raw MemoryError. The limit now bounds the memory available, so the refusal comes first."""
    import subprocess
    import sys

    script = (
        "import resource\n"
        "resource.setrlimit(resource.RLIMIT_AS, (3 * 10**9, resource.RLIM_INFINITY))\n"
        "from wmrjax import resources\n"
        "a = resources.available_bytes()\n"
        "assert 0 < a <= 3 * 10**9, a\n"
        "assert resources._machine_available() > a\n"
        "try:\n"
        "    resources.check_fits(resources.Estimate(0.0, 2.9e9), 'two point nine GB', 'less')\n"
        "except ValueError as err:\n"
        "    print(err)\n"
    )
    r = subprocess.run([sys.executable, "-c", script], cwd=ROOT, capture_output=True, text=True, timeout=120)
    assert r.returncode == 0, r.stderr[-2000:]
    assert "two point nine GB needs about 2.9 GB" in r.stdout and "available now" in r.stdout
