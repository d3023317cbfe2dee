"""The resource model against measured peaks: predicted memory of simulate, a sweep block and a
tuning step each above the measured peak and within ``resources.ESTIMATE_FACTOR`` of it
(``GRADIENT_ESTIMATE_FACTOR`` for the tuning step)
(measured in fresh processes as the growth of the peak resident memory, VmHWM, over a warm
baseline),
and the checks that refuse oversized work before compiling."""

import dataclasses
import json
import subprocess
import sys
from pathlib import Path

import pytest

from wmrjax import resources

ROOT = Path(__file__).resolve().parents[1]

# the peak resident memory of this process image (VmHWM): ru_maxrss would carry the parent's peak
# over fork and exec (a pytest worker's 2 GB hid the child's growth)
PEAK = (
    "def peak():\n"
    "    for line in open('/proc/self/status'):\n"
    "        if line.startswith('VmHWM:'):\n"
    "            return int(line.split()[1]) * 1024\n"
)

SIMULATE = (
    PEAK
    + """
import sys, json, jax
jax.config.update("jax_enable_x64", True)
import numpy as np
import wmrjax as w
from wmrjax import references as R, resources
from wmrjax.simulate import _check_memory
n, dt = int(sys.argv[1]), float(sys.argv[2])
ctrl = w.dynamic_linearization("(2,0)", "velocity")
p = ctrl.params(R.circle(radius=3.0, omega=0.5), poles=1.0)
z0 = ctrl.initial_state(ctrl.reference_jet(0.0, p)[:2] + 0.05, p)
w.simulate(ctrl, z0, p, dt=0.01, n_steps=10)
base = peak()
jax.block_until_ready(w.simulate(ctrl, z0, p, dt=dt, n_steps=n))
est = resources.run_estimate(ctrl, n_steps=n, save_every=1, n_state=4, itemsize=8, horizon=n * dt)
print(json.dumps({"measured": peak() - base, "predicted": est.total}))
"""
)

TUNE = (
    PEAK
    + """
import sys, json, jax
jax.config.update("jax_enable_x64", True)
from wmrjax import resources
from wmrjax.problem import Problem
from tuning import config, loop
prob = Problem.load("tuning/problems/section_6_1.toml")
setting = prob.setting("tuning")
ts = config.read(prob.section("tune"))
fam = ts.gain_spec(setting)
out = []
for n in (64, 2048):
    sc = ts.scenarios._replace(train=n, validation=4, heldout=4)
    loop.tune(setting, fam, ts.optimizer.build(1), steps=1, scenarios=sc, loss=ts.loss, stopping=ts.stopping,
              log=lambda *_: None)
    out.append(peak())
n_state = setting.system().n_state
pred = resources.gradient_bytes(2048, setting.n_steps, n_state) - resources.gradient_bytes(64, setting.n_steps, n_state)
print(json.dumps({"measured": out[1] - out[0], "predicted": pred}))
"""
)


def _measure(script, *args):
    r = subprocess.run(
        [sys.executable, "-c", script, *map(str, args)], cwd=ROOT, capture_output=True, text=True, timeout=600
    )
    assert r.returncode == 0, r.stderr[-3000:]
    return json.loads(r.stdout.strip().splitlines()[-1])


def _within(m, factor=resources.ESTIMATE_FACTOR):
    print(
        f"predicted {m['predicted'] / 1e6:.1f} MB, measured {m['measured'] / 1e6:.1f} MB, "
        f"ratio {m['predicted'] / m['measured']:.2f}"
    )
    assert m["measured"] <= m["predicted"] <= factor * m["measured"], m


@pytest.mark.parametrize(
    "n, dt",
    [
        (500_000, 0.02),  # the reference check dominates (1e4 s)
        (2_000_000, 1e-4),
    ],
)  # the saved samples dominate
def test_simulate_estimate_bounds_the_measured_peak(n, dt):
    """Before: the estimate counted the samples only, 0.96 GB against a 3.46 GB peak at 1e7 steps."""
    _within(_measure(SIMULATE, n, dt))


def test_tuning_step_estimate_bounds_the_measured_peak():
    """The growth from 64 to 2048 training scenarios (section 6.1's tuning problem, 1000 steps)."""
    _within(_measure(TUNE), resources.GRADIENT_ESTIMATE_FACTOR)


def test_sweep_block_estimate_bounds_the_measured_peak(tmp_path):
    """A block of 256 runs of 10000 steps saved every step, in one process of one device: the
    process's peak against the estimate with the process itself."""
    spec = tmp_path / "s.toml"
    spec.write_text((ROOT / "tests" / "data" / "memory_sweep.toml").read_text())
    script = (
        PEAK
        + """
import sys
from experiments.sweep import cli
rc = cli.main([sys.argv[1], "--out", sys.argv[2], "--devices", "1", "--no-compile-cache"])
import json, jax
from experiments.sweep import spec as S, run
est = run.estimate(S.load(sys.argv[1]), 1)
print(json.dumps({"measured": peak(), "predicted": est.total, "rc": rc}))
"""
    )
    m = _measure(script, spec, tmp_path / "out")
    assert m["rc"] == 0
    _within(m)


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
    """python -m tuning --n-train 1000000 failed allocating 14.6 GB after 6 s; a sweep of 256
    runs of 400000 samples each asked for 8.3 GB per device with no estimate."""
    from experiments.sweep import run as sweep_run
    from experiments.sweep import spec as S
    from tuning import config, loop
    from wmrjax.problem import Problem

    monkeypatch.setattr(resources, "available_bytes", lambda: 8 * 10**9)
    prob = Problem.load(ROOT / "tuning" / "problems" / "section_6_1.toml")
    setting = prob.setting("tuning")
    sc = config.read(prob.section("tune")).scenarios
    loop.check_memory(setting, sc)
    with pytest.raises(
        ValueError,
        match=r"a gradient step over 1000000 training scenarios of 1000 steps needs about "
        r"130 GB .* lower the training scenarios \(--n-train\)",
    ):
        loop.check_memory(setting, sc._replace(train=10**6))
    plan = S.load(ROOT / "tests" / "data" / "memory_sweep.toml")
    sweep_run.check_memory(plan, 1)
    with pytest.raises(ValueError, match=r"2 process\(es\) x 2 device\(s\), each running a block of 256 runs"):
        sweep_run.check_memory(dataclasses.replace(plan, n_steps=400_000), 2, 2)
