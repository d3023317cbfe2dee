"""The exported control step (wmrjax.export, wmrjax export): the JAX step is the
simulator's sample, the generated C (compiled warning-free at -std=c99 -Wall -Wextra -Werror -O2)
and the serialized artifact (reloaded in a process where wmrjax cannot be imported) agree with
it over whole closed-loop runs; bad input is refused."""

import json
import shutil
import subprocess
import sys
from pathlib import Path

import jax
import jax.numpy as jnp
import numpy as np
import pytest

import wmrjax as w
from wmrjax import _cgen
from wmrjax import export as X
from wmrjax import references as R
from wmrjax.export import check as E

ROOT = Path(__file__).resolve().parent.parent
CC = shutil.which("cc")
needs_cc = pytest.mark.skipif(CC is None, reason="no C compiler on PATH")


def _checked(tmp_path, ctrl, params, z0, period, n_samples):
    step = X.control_step(ctrl, params)
    E.write_export(step, tmp_path)
    run = X.reference_run(step, ctrl, params, z0, period=period, n_samples=n_samples)
    assert run.complete and len(run.t) == n_samples
    return step, E.verify(step, run, period=period, directory=tmp_path, cc=CC)


@needs_cc
def test_section_6_1_step_c_and_artifact_agree_over_a_run(tmp_path):
    """The paper's §6.1 loop (2,0), e = 0, poles -1, reference (62), initial condition (63): 500
    periods of 10 ms. Measured: JAX step vs simulator 9e-16, C vs JAX 5e-16, artifact 0."""
    from paper import common

    ctrl, params, z0, _ = common.section_6_1_setup()
    step, c = _checked(tmp_path, ctrl, params, z0, 0.01, 500)
    assert c["jax_vs_simulator"] <= 1e-12 and c["c_vs_jax"] <= 1e-12 and c["artifact_vs_jax"] <= 1e-14
    assert c["jax_driven_vs_simulator"] <= 1e-12  # its own compensator, driven over the whole run
    assert c["artifact_imported_wmrjax"] is False and 0 < c["c_seconds_per_step"] < 1e-3
    header = (tmp_path / f"{step.name}.h").read_text()
    assert f"#define {step.name.upper()}_N_STATE 3" in header and "_step(double t" in header


@needs_cc
def test_torque_level_static_step_agrees_on_a_sampled_path(tmp_path):
    """Torque level on a path sampled at 10 Hz (the spline's pieces as a constant table), a static
    law, whose state is the plant's (every dynamic torque-level law: the benchmark's export block)."""
    ctrl = w.static_linearization("(2,0)", "torque")
    circle = R.circle(radius=2.0, omega=0.4)
    ts = np.linspace(0.0, 12.0, 121)
    ref = R.from_samples(ts, np.asarray(jax.vmap(circle.position)(jnp.asarray(ts))))
    params = ctrl.params(ref, poles=1.5, geometry=ctrl.row.default_geometry)
    X0 = jnp.array([2.05, 0.0, jnp.pi / 2])
    z0 = ctrl.initial_state_from_physical(X0, jnp.array([0.8, 0.4]), params)
    step, c = _checked(tmp_path, ctrl, params, z0, 0.05, 200)
    assert step.n_state == 0
    assert "static const double table" in (tmp_path / f"{step.name}.c").read_text()
    assert c["jax_vs_simulator"] <= 1e-12 and c["c_vs_jax"] <= 1e-12 and c["artifact_vs_jax"] <= 1e-14


@needs_cc
def test_command_exports_a_problem_file_and_the_robot_loop_compiles(tmp_path):
    """wmrjax export on the user-path problem (20 Hz controller, sampled path):
    files, summary, agreement; the robot-loop example builds against the generated code and runs."""
    out = tmp_path / "export"
    r = subprocess.run(
        [sys.executable, "-m", "wmrjax", "export", "wmrjax/examples/s_path.toml", "--out", str(out),
         "--samples", "100", "--initial", "3"],
        cwd=ROOT, capture_output=True, text=True, timeout=600,
    )  # fmt: skip
    assert r.returncode == 0, r.stderr[-2000:]
    s = json.loads((out / "summary.json").read_text())
    assert s["agrees"] and s["checks"]["samples"] == 100 and s["checks"]["period_s"] == 0.05
    assert s["initial_condition"]["index"] == 3  # --initial is used (it was parsed and ignored)
    assert set(s["files"]) == {"wmr_20_velocity.h", "wmr_20_velocity.c", "wmr_20_velocity.jax_export", "robot_loop.c"}
    exe = tmp_path / "robot"
    subprocess.run([CC, *E.C_FLAGS, "robot_loop.c", "wmr_20_velocity.c", "-o", str(exe), "-lm"], cwd=out, check=True)
    printed = subprocess.run([str(exe)], capture_output=True, text=True, check=True).stdout
    assert printed.startswith("command after 10 periods:")


def test_bad_input_is_refused_before_any_work(tmp_path):
    from paper import common

    ctrl, params, _, _ = common.section_6_1_setup()
    with pytest.raises(ValueError, match="C identifier"):
        X.control_step(ctrl, params, name="2fast")
    with pytest.raises(ValueError, match="linearizing law"):
        X.control_step(w.hybrid_parking(), params)
    with pytest.raises(ValueError, match="compensator must have 1 values"):
        X.control_step(ctrl, params).initial_state(0.0, [1.0, 2.0])
    # a primitive without a C rule is named, never approximated
    closed = jax.make_jaxpr(lambda t, m, s: (jax.lax.while_loop(lambda x: x[0] < 1.0, lambda x: x + t, m), s, t))(
        1.0, jnp.zeros(1), jnp.zeros(0)
    )
    sig = _cgen.Signature("f", 1, 0, 1, 0, ("x",), ("u",), (), "(2,0)", "velocity")
    with pytest.raises(ValueError, match="'while' has no C rule"):
        _cgen.generate(closed, sig)
    r = subprocess.run(
        [sys.executable, "-m", "wmrjax", "export", "--cc", "no-such-cc", "--out", str(tmp_path / "o")],
        cwd=ROOT, capture_output=True, text=True,
    )  # fmt: skip
    assert r.returncode == 2 and "no such compiler" in r.stderr
    r = subprocess.run(
        [sys.executable, "-m", "wmrjax", "export", "--initial", "99999", "--cc", "none", "--out", str(tmp_path / "o2")],
        cwd=ROOT, capture_output=True, text=True,
    )  # fmt: skip
    assert r.returncode == 2 and "--initial 99999: the problem has 6561 initial conditions" in r.stderr
    assert not (tmp_path / "o2").exists()


@needs_cc
def test_the_export_job_returns_its_typed_report(tmp_path):
    """wmrjax.export.job.run from Python: the report's fields are the summary on disk, and its
    agreement is the checks' against the tolerance."""
    from wmrjax.export import job
    from wmrjax.problem import Problem

    problem = Problem.load(ROOT / "wmrjax/examples/section_6_1.toml")
    r = job.run(tmp_path, problem, n_samples=20, cc=CC, progress=lambda m: None)
    on_disk = json.loads((tmp_path / "summary.json").read_text())
    assert isinstance(r, job.ExportReport) and json.loads(json.dumps(r.summary())) == on_disk
    assert r.agrees and on_disk["agrees"] and r.checks["samples"] == 20
    assert set(r.files) == {f"{r.step.name}.h", f"{r.step.name}.c", f"{r.step.name}.jax_export", "robot_loop.c"}
    assert r.initial_compensator.shape == (r.step.n_compensator,)
    strict = job.ExportReport(**{**r.__dict__, "tolerance": 0.0})  # nothing agrees to 0 but exact equality
    assert strict.agrees == (max(r.checks[k] for k in ("jax_vs_simulator", "artifact_vs_jax", "c_vs_jax")) == 0.0)
