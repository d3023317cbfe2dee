"""A user's problem: its file form (every section, round trips, cases, gains files), the one
placement of an initial state, and the one run."""

import json
import pathlib

import jax
import jax.numpy as jnp
import numpy as np
import pytest

import wmrjax as w
from wmrjax.problem import JOB_SECTIONS, Problem, ProblemError, Space, Task, gains_file_dict, place, read_gains_file

ROOT = pathlib.Path(__file__).resolve().parents[1]
S_PATH = ROOT / "wmrjax" / "examples" / "s_path.toml"

BASE = {
    "controller": {"law": "dynamic", "robot": "(2,0)"},
    "geometry": {"e": 0.15},
    "reference": {"family": "circle", "options": {"radius": 3.0}},
    "initial": {"space": "output", "x": 0.1},
    "simulation": {"t_final": 2.0, "dt": 0.01},
}


def test_the_example_round_trips_through_its_resolved_form():
    """The resolved problem (files inlined) builds the same settings as the file, from anywhere."""
    p = Problem.load(S_PATH)
    data = json.loads(json.dumps(p.resolved()))  # plain JSON
    assert "file" not in data["reference"] and len(data["reference"]["t"]) == 401
    assert data["reference"]["source_file"]["path"].endswith("s_path.csv")
    q = Problem.from_dict(data, base="/")
    a, b = p.setting("test"), q.setting("test")
    assert a.shape == b.shape == (1, 1, 1, 1, 256) and a.steps_per_sample == 5 and a.noise_std == (0.01, 0.01, 0.005)
    for x, y in zip(jax.tree_util.tree_leaves(a.inputs()), jax.tree_util.tree_leaves(b.inputs())):
        np.testing.assert_array_equal(np.asarray(x), np.asarray(y))
    assert p.fingerprint() == q.fingerprint()


def test_samples_from_arrays_equal_samples_from_the_file(tmp_path):
    t = np.linspace(0.0, 5.0, 26)
    xy = np.stack([t, np.sin(t)], axis=1)
    (tmp_path / "p.csv").write_text(
        "\ufeff# a BOM and a comment\nt,x,y\n" + "".join(f"{a},{b},{c}\n" for a, (b, c) in zip(t, xy))
    )
    f = Problem.from_dict({**BASE, "reference": {"family": "samples", "file": "p.csv"}}, base=tmp_path)
    a = Problem.from_dict(
        {**BASE, "reference": {"family": "samples", "t": t.tolist(), "x": xy[:, 0].tolist(), "y": xy[:, 1].tolist()}}
    )
    for x, y in zip(
        jax.tree_util.tree_leaves(f.setting("t").reference.params),
        jax.tree_util.tree_leaves(a.setting("t").reference.params),
    ):
        np.testing.assert_array_equal(np.asarray(x), np.asarray(y))
    wp = (
        Problem.from_dict(
            {**BASE, "reference": {"family": "waypoints", "x": xy[:, 0].tolist(), "y": xy[:, 1].tolist(), "speed": 1.2}}
        )
        .setting("t")
        .reference
    )
    np.testing.assert_allclose(np.asarray(wp.position(0.0)), [0.0, 0.0], atol=1e-12)
    (tmp_path / "dup.csv").write_text("t,x,y,x\n" + "".join(f"{a},{b},{c},0\n" for a, (b, c) in zip(t, xy)))
    with pytest.raises(ProblemError, match=r"column\(s\) \['x'\] appear more than once"):
        Problem.from_dict({**BASE, "reference": {"family": "samples", "file": "dup.csv"}}, base=tmp_path)
    with pytest.raises(ProblemError, match="file = .* or the arrays t, x, y"):
        Problem.from_dict({**BASE, "reference": {"family": "samples", "file": "p.csv", "t": [0.0]}}, base=tmp_path)


def test_gains_in_every_form_and_files_of_another_controller(tmp_path):
    ctrl = w.dynamic_linearization("(2,0)", "velocity")
    tuned = w.Gains.from_damping(2.0, 0.5, m=2)
    (tmp_path / "tuned.json").write_text(json.dumps(gains_file_dict(tuned, ctrl)))
    other = w.dynamic_linearization("(2,0)", "torque")
    (tmp_path / "torque.json").write_text(json.dumps(gains_file_dict(w.Gains.from_poles(1.0, 2, 3), other)))
    forms = {
        "poles": {"poles": [1.0, 2.0]},
        "damping": {"omega": 2.0, "zeta": 0.5},
        "coefficients": {"coefficients": [4.0, 2.0]},
        "file": {"file": ["tuned.json"]},
    }
    coeffs = {}
    for name, g in forms.items():
        s = Problem.from_dict({**BASE, "gains": g}, base=tmp_path).settings()[0]
        coeffs[name] = np.asarray(s.axis("gains").payload["gains"].coeffs)
    assert coeffs["poles"].shape == (2, 2, 2)
    np.testing.assert_allclose(coeffs["damping"][0], [[4.0, 2.0]] * 2, rtol=1e-15)
    np.testing.assert_array_equal(coeffs["coefficients"], coeffs["damping"])
    np.testing.assert_array_equal(coeffs["file"], coeffs["damping"])
    assert read_gains_file(tmp_path / "tuned.json").robot == "(2,0)"
    with pytest.raises(
        ProblemError,
        match="gains tuned for type \\(2,0\\) at torque level \\(dynamic law\\), this controller is type "
        "\\(2,0\\) at velocity level",
    ):
        Problem.from_dict({**BASE, "gains": {"file": "torque.json"}}, base=tmp_path)
    # the same shape, another robot: (1,1) at velocity level has gains of (2,0)'s shape
    same_shape = gains_file_dict(tuned, w.dynamic_linearization("(1,1)", "velocity"))
    (tmp_path / "t11.json").write_text(json.dumps(same_shape))
    with pytest.raises(
        ProblemError,
        match="gains tuned for type \\(1,1\\) at velocity level \\(dynamic law\\), this controller is type \\(2,0\\)",
    ):
        Problem.from_dict({**BASE, "gains": {"file": "t11.json"}}, base=tmp_path)
    # a tuning summary says whose gains they are in its resolved problem (it was not read: accepted)
    summary = {
        "problem": {"controller": {"law": "dynamic", "robot": "(1,1)", "level": "velocity"}},
        "tuned_gains": {"coefficients_k0_to_kr-1": np.asarray(tuned.coeffs).tolist()},
    }
    (tmp_path / "summary.json").write_text(json.dumps(summary))
    with pytest.raises(ProblemError, match="gains tuned for type \\(1,1\\)"):
        Problem.from_dict({**BASE, "gains": {"file": "summary.json"}}, base=tmp_path)
    # the probe's gains-summary-own-robot: a summary of a problem that left the level to its
    # default was refused as not saying whose gains they are; the level defaults as the file's did
    # (and a current summary says robot, level and law itself)
    summary["problem"]["controller"] = {"law": "dynamic", "robot": "(2,0)"}
    (tmp_path / "summary.json").write_text(json.dumps(summary))
    p = Problem.from_dict({**BASE, "gains": {"file": "summary.json"}}, base=tmp_path)
    np.testing.assert_array_equal(np.asarray(p.setting("t").gains().coeffs), np.asarray(tuned.coeffs))
    summary.update(robot="(1,1)", level="velocity", law="dynamic")
    (tmp_path / "summary.json").write_text(json.dumps(summary))
    with pytest.raises(ProblemError, match="gains tuned for type \\(1,1\\)"):
        Problem.from_dict({**BASE, "gains": {"file": "summary.json"}}, base=tmp_path)
    (tmp_path / "anon.json").write_text(
        json.dumps({k: v for k, v in same_shape.items() if k not in ("robot", "level")})
    )
    with pytest.raises(ProblemError, match="does not say which robot type and level"):
        Problem.from_dict({**BASE, "gains": {"file": "anon.json"}}, base=tmp_path)
    with pytest.raises(ProblemError, match="not a regular file"):
        Problem.from_dict({**BASE, "gains": {"file": "/dev/zero"}}, base=tmp_path)
    with pytest.raises(ProblemError, match="a file listed twice"):
        Problem.from_dict({**BASE, "gains": {"file": ["tuned.json", "tuned.json"]}}, base=tmp_path)
    with pytest.raises(ProblemError, match=r"\[gains\] file: expected a path, or a list of paths"):
        Problem.from_dict({**BASE, "gains": {"file": [1]}}, base=tmp_path)
    with pytest.raises(ProblemError, match="give one of poles, omega and zeta"):
        Problem.from_dict({**BASE, "gains": {"poles": 1.0, "coefficients": [1.0, 2.0]}})
    sched = {"knots": [0.0, 2.0], "omega": [[[1.0]] * 2] * 2, "zeta": [[[1.0]] * 2] * 2}
    g = Problem.from_dict({**BASE, "gains": {"schedule": sched}}).setting("t").gains()
    assert g.time_varying and np.allclose(np.asarray(g.coeffs_at(1.0)), [[1.0, 2.0]] * 2)


def test_cases_pair_settings_and_jobs_take_one():
    p = Problem.from_dict({**BASE, "case": [{"name": "default"}, {"name": "fast", "gains": {"poles": 2.0}}]})
    s = p.settings()
    assert [x.case for x in s] == ["default", "fast"]
    assert float(s[1].gains().coeffs[0, 0]) == 4.0 and float(s[0].gains().coeffs[0, 0]) == 1.0
    with pytest.raises(ProblemError, match="tuning takes one controller: this problem has 2 settings"):
        p.setting("tuning")
    assert p.setting("x", case="fast").case == "fast"
    with pytest.raises(ProblemError, match="no case named 'slow'"):
        p.setting("x", case="slow")
    with pytest.raises(ProblemError, match="not used by another case"):
        Problem.from_dict({**BASE, "case": [{"name": "a"}, {"name": "a"}]})
    with pytest.raises(ProblemError, match=r"\[controller\] robot: listed twice"):
        Problem.from_dict({**BASE, "controller": {"law": "dynamic", "robot": ["(2,0)", "(2,0)"]}})
    # a value listed twice on any axis ran and counted its runs twice (the probe's BAD cases)
    with pytest.raises(ProblemError, match=r"\[gains\] poles: 1.0 listed twice in \[1.0, 1.0\]"):
        Problem.from_dict({**BASE, "gains": {"poles": [1.0, 1.0]}})
    with pytest.raises(ProblemError, match=r"\[initial\] x: 0.0 listed twice"):
        Problem.from_dict({**BASE, "initial": {"space": "output", "x": [0.0, 0.0, 0.7]}})
    with pytest.raises(ProblemError, match=r"\[plant\] input_limit: \[2.0, 1.0\] listed twice"):
        Problem.from_dict({**BASE, "plant": {"input_limit": [[2.0, 1.0], [2.0, 1.0]]}})
    assert Problem.from_dict({**BASE, "plant": {"input_limit": [2.0, 2.0]}}).setting("x").plant  # one vector
    q = Problem.from_dict(BASE).with_values({"plant.input_limit": [1.0, 2.0], "geometry.e": 0.2})
    assert q.data["plant"] == {"input_limit": [1.0, 2.0]} and q.setting("x").plant
    with pytest.raises(ProblemError, match=r"\[plant\] control_period = 0.013 s is not a whole number of steps"):
        q.with_values({"plant.control_period": 0.013})


def test_place_puts_the_error_where_it_says():
    """Output space: the placed state's output error is the given one (position and velocity
    rows, or the whole jet); physical space: the posture is the reference's plus the error; a
    static point law's tracked point is the reference's position plus (x, y)."""
    ctrl = w.dynamic_linearization("(2,0)", "velocity")
    params = ctrl.params(w.references.circle(radius=3.0), geometry=w.Geometry(e=0.15))
    d = jnp.array([0.3, -0.2, 0.1, 0.05])
    err = ctrl.error(0.0, place(ctrl, params, d, Space.OUTPUT, Task.POSTURE, 1.0), params)
    np.testing.assert_allclose(np.asarray(err).reshape(-1), np.asarray(d), atol=1e-13)
    z = place(ctrl, params, jnp.array([0.3, -0.2, 0.1]), "physical", "posture", 1.0)
    np.testing.assert_allclose(np.asarray(z[:3] - ctrl.reference_state(0.0, params)[:3]), [0.3, -0.2, 0.1], atol=1e-14)
    st = w.controller("(2,0)", level="velocity", task="point")
    sp = st.params(w.references.circle(radius=3.0), geometry=st.row.default_geometry)
    X = place(st, sp, jnp.array([0.3, -0.2, 0.4]), Space.PHYSICAL, Task.POINT, 1.0)
    np.testing.assert_allclose(
        np.asarray(st.law.outputs(X, sp.geometry)[:2] - sp.reference.position(0.0)), [0.3, -0.2], atol=1e-13
    )
    assert abs(float(X[2]) - float(sp.reference.posture(0.0)[2]) - 0.4) < 1e-14


def test_one_run_is_the_sweeps_run():
    """Setting.run of a run's inputs equals the sweep's rollout of that run (one run in the library),
    a digital controller with noise drawn from the run's index included."""
    from wmrjax.sweep import run as sweep_run
    from wmrjax.sweep import spec as S

    p = Problem.from_dict(
        {
            **BASE,
            "plant": {
                "input_limit": [2.0, 1.0],
                "control_period": 0.05,
                "noise_std": [0.01, 0.01, 0.005],
                "noise_seed": 3,
            },
            "initial": {"space": "output", "x": [0.1, -0.2], "y": 0.3},
        }
    )
    plan = S.plan(p)
    g = plan.groups[0]
    one = jax.jit(sweep_run.rollout_fn(plan, g))
    _, constant, _ = sweep_run.split(g)
    leaves = sweep_run.payload(g, 1, 1, 1, constant)
    got = one([x[0] for x in leaves])
    tr, _ = g.run(
        g.run_inputs(1),
        save_every=plan.save_every,
        error_tol=plan.error_tol,
        noise_key=jax.random.fold_in(jax.random.PRNGKey(3), 1),
    )
    # (to rounding: the sweep compiles the run's fixed inputs in as constants, which XLA folds)
    np.testing.assert_allclose(float(got["min_margin"]), float(tr.diagnostics.min_margin), rtol=1e-13)
    assert bool(got["failed"]) == bool(tr.diagnostics.failed) is False
    zf = np.asarray(tr.final_state.plant[:2])
    pos = np.hypot(*(zf - np.asarray(g.reference.posture(2.0)[:2])))
    np.testing.assert_allclose(float(got["final_position_error"]), pos, rtol=1e-12)


@pytest.mark.parametrize(
    "key, value, message",
    [
        ("certify.epz", 1, r"\[certify\]: unknown key\(s\) \['epz'\]"),
        ("certify.eps", 0, r"\[certify\] eps: expected a number > 0"),
        ("classify.position_tol", -1, r"\[classify\] position_tol: expected a number > 0"),
        ("tune.steps", 0, r"\[tune\] steps: expected an integer >= 1, got 0"),
        ("tune.loss.tracking", -1, r"\[tune.loss\] tracking"),
    ],
)
def test_every_job_section_is_validated_when_the_file_is_loaded(key, value, message):
    """[tune], [certify] and [classify] are checked with the rest of the file (by the schema their
    job contributes: wmrjax.problem.JOB_SECTIONS), not only by the job that reads them: a sweep
    of a file whose [certify] has a typo is refused too."""
    good = Problem.load(S_PATH)
    assert set(JOB_SECTIONS) == {"tune", "certify", "classify"}
    with pytest.raises(ValueError, match=message):
        good.with_values({key: value})
