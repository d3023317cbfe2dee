"""Identification from logs (wmrjax.identify): the model against SciPy, the fit's estimates and
intervals on logs integrated by SciPy (tests/identify_oracle.py, not wmrjax.simulate), the
parameters no log determines, the refused logs, and the identified [plant] back in a problem."""

import json
import math
import pathlib
import tomllib

import jax.numpy as jnp
import numpy as np
import pytest
from identify_oracle import make_log

import wmrjax as w
from wmrjax import identify as I
from wmrjax.controllers.law import Level
from wmrjax.problem import Problem

ROOT = pathlib.Path(__file__).resolve().parents[1]
CAR = ROOT / "wmrjax" / "examples" / "car_waypoints.toml"
PERIOD = 0.02
NOISE = {"(2,0)": [0.01, 0.01, 0.005], "(1,1)": [0.01, 0.01, 0.005, 0.005]}


def synthetic(kind, level, geometry_scale, input_scale, n, seed, noise=None, **kw):
    """A SciPy-integrated log (identify_oracle) of this file's car geometry and 50 Hz period; the
    type's noise unless ``noise`` is given."""
    noise = NOISE[kind] if noise is None else noise
    return make_log(
        kind, level, L=0.33, geometry_scale=geometry_scale, input_scale=input_scale, noise_std=noise, n=n,
        period=PERIOD, seed=seed, **kw,
    )  # fmt: skip


def model(kind, level, limit=(math.inf, math.inf)):
    return I.PlantModel(w.robot_type(kind), Level(level), w.Geometry(0.33, 0.25, 0.0), limit, PERIOD)


@pytest.fixture(scope="module")
def car_velocity():
    """Two 8 s logs of a (1,1) car at velocity level: L 6 % long, input scales 0.92 and 1.04."""
    logs = [synthetic("(1,1)", "velocity", 1.06, [0.92, 1.04], 401, s, name=f"log{s}") for s in range(2)]
    return logs, I.identify(model("(1,1)", "velocity"), logs)


def test_the_open_loop_model_is_scipys_integration():
    """predict (RK4 through simulate, 4 steps per period) against DOP853 at 1e-12 on a noise-free
    (1,1) torque-level log: the same states to RK4's error at h = 5 ms."""
    log = synthetic("(1,1)", "torque", 1.1, [0.9, 1.05], 101, 3, noise=0.0)
    m = model("(1,1)", "torque")
    p = I.InputParams(
        w.Geometry(0.33 * 1.1, 0.25 * 1.1, 0.0), jnp.array([0.9, 1.05]), jnp.full(2, jnp.inf), jnp.asarray(log.command)
    )
    z0 = jnp.concatenate([jnp.asarray(log.posture[0]), jnp.array([0.8, 0.0])])
    X = np.asarray(I.predict(m.system, z0, p, PERIOD))[:, :4]
    d = X - log.posture
    d[:, 2] = np.arctan2(np.sin(d[:, 2]), np.cos(d[:, 2]))
    assert np.max(np.abs(d)) < 1e-8


def test_the_jacobian_is_finite_differences():
    """The fit's forward-mode Jacobian in the plant's parameters against central differences."""
    log = synthetic("(1,1)", "velocity", 1.0, 1.0, 41, 1, noise=0.0)
    m = model("(1,1)", "velocity")
    seg = I.fit.cut(m, [log], 40, 0, 0)
    theta = np.array([1.05, 0.95, 1.02])
    r, jt, _ = (
        np.asarray(a)
        for a in I.fit._evaluate(m, (0, 1, 2), jnp.asarray(theta), seg.initial, seg.commands, seg.measured)
    )
    for k in range(3):
        e = np.zeros(3)
        e[k] = 1e-6
        rp = np.asarray(
            I.fit._evaluate(m, (0, 1, 2), jnp.asarray(theta + e), seg.initial, seg.commands, seg.measured)[0]
        )
        rm = np.asarray(
            I.fit._evaluate(m, (0, 1, 2), jnp.asarray(theta - e), seg.initial, seg.commands, seg.measured)[0]
        )
        np.testing.assert_allclose(jt[..., k], (rp - rm) / 2e-6, atol=1e-8)


def test_a_car_is_identified_within_its_intervals(car_velocity):
    """(1,1) velocity level: every parameter and noise std within its 95 % interval, the intervals
    narrow (the logs excite every input), the residuals at the noise level."""
    _, ident = car_velocity
    truth = {"geometry_scale": 1.06, "input_scale_1": 0.92, "input_scale_2": 1.04}
    truth |= {f"noise_std_{c}": s for c, s in zip(("x", "y", "theta", "beta1"), NOISE["(1,1)"])}
    assert ident.converged
    for name, v in truth.items():
        e = ident.estimate(name)
        assert e.identifiable and e.interval_95[0] <= v <= e.interval_95[1], (name, e)
        assert e.std_error < (0.04 if name.startswith("noise") else 0.02) * v  # noise: 1 / sqrt(2 * 800)
    np.testing.assert_allclose(ident.residual_rms, np.broadcast_to(NOISE["(1,1)"], ident.residual_rms.shape), rtol=0.15)
    s = json.loads(json.dumps(ident.summary()))
    assert set(s["parameters"]) == {"geometry_scale", "input_scale_1", "input_scale_2"}
    assert s["parameters"]["geometry_scale"]["interval_95"] == list(ident.parameters[0].interval_95)


@pytest.fixture(scope="module")
def diff_drive():
    """A 6 s log of a (2,0) robot at torque level: input scales 1.1 and 0.9 (its L and e are not seen)."""
    log = synthetic("(2,0)", "torque", 1.3, [1.1, 0.9], 301, 7)
    return I.identify(model("(2,0)", "torque"), [log])


def test_e_of_a_differential_robot_is_not_identifiable_and_a_torque_level_one_is_fitted(diff_drive):
    """(2,0) at torque level: geometry_scale is not seen by the kinematics (named, no number); the
    input scales are recovered within their intervals."""
    ident = diff_drive
    g = ident.estimate("geometry_scale")
    assert not g.identifiable and g.estimate is None and g.interval_95 is None and "do not see" in g.note
    for name, v in (("input_scale_1", 1.1), ("input_scale_2", 0.9)):
        e = ident.estimate(name)
        assert e.identifiable and e.interval_95[0] <= v <= e.interval_95[1], (name, e)
    assert ident.summary()["parameters"]["geometry_scale"]["estimate"] is None


def test_a_delay_is_found():
    """Commands applied two samples late: the likelihood selects a delay of 2 among 0..3."""
    log = synthetic("(2,0)", "velocity", 1.0, [1.0, 1.0], 301, 2)
    late = log._replace(command=np.concatenate([log.command[2:], np.repeat(log.command[-1:], 2, axis=0)]))
    ident = I.identify(model("(2,0)", "velocity"), [late], I.FitOptions(max_delay=3))
    assert ident.delay == 2
    assert np.argmin(ident.delay_nll) == 2 and ident.delay_nll[2] < min(ident.delay_nll[:2]) - 10


def _write(path, header, rows):
    path.write_text(header + "\n" + "\n".join(",".join(repr(float(v)) for v in r) for r in rows) + "\n")
    return path


def _rows(n=5):
    t = np.arange(n) * PERIOD
    return np.column_stack([t, 0.1 * t, np.zeros(n), np.zeros(n), np.full(n, 0.8), np.zeros(n)])


@pytest.mark.parametrize(
    "edit, expected",
    [
        (lambda h, r: (h, r[:1]), "1 sample(s); a fit needs at least two"),
        (
            lambda h, r: (h, np.where(np.arange(r.size).reshape(r.shape) == 13, np.nan, r)),
            "data row 3, column 'x' is nan",
        ),
        (lambda h, r: (h, r[[0, 2, 1, 3, 4]]), "data row 3 has t = 0.02 s, not after row 2's 0.04 s"),
        (lambda h, r: (h.replace(",u2", ",v2"), r), "missing column(s) ['u2']"),
        (lambda h, r: (h, r * np.array([2.5, 1, 1, 1, 1, 1])), "not the controller period 0.02 s"),
        (lambda h, r: (h + ",beta1", np.column_stack([r, np.zeros(len(r))])), "['beta1'] belong to another robot type"),
    ],
    ids=["one_sample", "nan", "time_back", "missing_column", "period", "other_robot"],
)
def test_bad_logs_are_refused_naming_the_row_or_column(tmp_path, edit, expected):
    header, rows = edit("t,x,y,theta,u1,u2", _rows())
    m = model("(2,0)", "velocity")
    with pytest.raises(ValueError) as err:
        I.check_log(I.read_log(_write(tmp_path / "log.csv", header, rows), m.robot), PERIOD, m.input_limit)
    assert expected in str(err.value)


def test_saturated_commands_are_reported_not_refused(tmp_path):
    rows = _rows()
    rows[1, 4] = 5.0
    m = model("(2,0)", "velocity", limit=(2.0, math.inf))
    check = I.check_log(
        I.read_log(_write(tmp_path / "log.csv", "t,x,y,theta,u1,u2", rows), m.robot), PERIOD, m.input_limit
    )
    assert check.saturated == (1, 0) and check.n_samples == 5


SECTION_6_1 = ROOT / "wmrjax" / "examples" / "section_6_1.toml"
PLANT = "[plant]\ninput_limit = [3.0, 2.0]   # kept\ncontrol_period = 0.02\ngeometry_scale = [0.95, 1.05]\n\n"


def _with_plant() -> str:
    text = SECTION_6_1.read_text()
    return text.replace("[reference]", PLANT + "[reference]", 1)


def test_a_vector_input_scale_in_a_problem_file():
    """[plant] input_scale: a list of lists is one factor per input (an axis of such vectors); a list of
    numbers stays an axis of one common factor; a vector of the wrong length is refused."""
    data = tomllib.loads(_with_plant())
    data["plant"]["input_scale"] = [[0.9, 1.1], [1.0, 1.05]]
    p = Problem.from_dict(data).setting("sweep").axis("plant").payload
    np.testing.assert_array_equal(
        p["input_scale"], np.repeat([[0.9, 1.1], [1.0, 1.05]], 2, axis=0)
    )  # product: geometry fastest
    data["plant"]["input_scale"] = [0.9, 1.1]
    p = Problem.from_dict(data).setting("sweep").axis("plant").payload
    assert p["input_scale"].shape == (4, 2) and set(map(tuple, p["input_scale"])) == {(0.9, 0.9), (1.1, 1.1)}
    data["plant"]["input_scale"] = [[0.9, 1.1, 1.0]]
    with pytest.raises(ValueError, match="input_scale"):
        Problem.from_dict(data)


def test_the_identified_plant_goes_into_the_problem(diff_drive):
    """plant_section: the 95 % intervals as listed ranges (the input scales' box corners), the
    problem's limits, period and non-identified geometry range kept (with the reason);
    with_plant_section replaces [plant] (and appends one to a problem without); the problem loads
    and its plant axis lists exactly those values."""
    ident = diff_drive
    text = _with_plant()
    section = I.sections.plant_section(ident, tomllib.loads(text)["plant"], "log0")
    assert "# geometry_scale not identified: the logs do not see it" in section
    data = tomllib.loads(I.sections.with_plant_section(text, section))
    assert data["plant"]["input_limit"] == [3.0, 2.0] and data["plant"]["control_period"] == 0.02
    assert data["plant"]["geometry_scale"] == [0.95, 1.05]
    s1, s2 = (ident.parameters[i].interval_95 for i in (1, 2))
    assert data["plant"]["input_scale"] == [[s1[0], s2[0]], [s1[0], s2[1]], [s1[1], s2[0]], [s1[1], s2[1]]]
    assert data["plant"]["noise_std"] == [e.interval_95[1] for e in ident.noise_std]
    assert {k: v for k, v in data.items() if k != "plant"} == tomllib.loads(SECTION_6_1.read_text())  # the rest kept
    assert Problem.from_dict(data).setting("sweep").axis("plant").size == 8
    appended = tomllib.loads(I.sections.with_plant_section(SECTION_6_1.read_text(), section))
    assert appended["plant"] == data["plant"]


def test_the_command_writes_the_identified_problem(tmp_path, returns):
    """wmrjax identify: summary.json's parameters block, plant.toml, a problem.toml
    that loads, the figure, the job's typed report; a bad log is refused before anything runs
    (status 2, the row named)."""
    from wmrjax.cli import identify as cli
    from wmrjax.identify import job

    log = synthetic("(1,1)", "torque", 1.05, [0.95, 1.0], 201, 4)
    path = _write(tmp_path / "run.csv", "t,x,y,theta,beta1,u1,u2", np.column_stack([log.t, log.posture, log.command]))
    out = tmp_path / "out"
    reports = returns(cli, "run")
    assert cli.main([str(CAR), "--log", str(path), "--out", str(out)]) == 0  # the session's compilation cache
    s = json.loads((out / "summary.json").read_text())
    (r,) = reports  # the command line printed from this report and wrote its summary
    assert isinstance(r, job.IdentifyReport) and json.loads(json.dumps(r.summary())) == s
    assert r.identification.estimate("geometry_scale").estimate == s["parameters"]["geometry_scale"]["estimate"]
    assert r.plant_section == (out / "plant.toml").read_text()
    assert s["parameters"]["geometry_scale"]["identifiable"] and set(s["files"]) == {
        "summary.json",
        "plant.toml",
        "problem.toml",
        "paths.png",
    }
    assert Problem.load(out / "problem.toml").setting("sweep").axis("plant").size == 8
    bad = _write(
        tmp_path / "bad.csv", "t,x,y,theta,beta1,u1,u2", np.column_stack([log.t, log.posture, log.command])[:1]
    )
    with pytest.raises(SystemExit) as exit_:
        cli.main([str(CAR), "--log", str(bad), "--out", str(tmp_path / "o2")])
    assert exit_.value.code == 2 and not (tmp_path / "o2").exists()


def test_a_parquet_log_reads_as_its_csv(tmp_path):
    """The command reads Parquet logs (pyarrow, the cli extra) into the same Log as the CSV."""
    import pyarrow as pa
    import pyarrow.parquet as pq

    from wmrjax.cli import identify as cli

    rows = _rows()
    names = ["t", "x", "y", "theta", "u1", "u2"]
    pq.write_table(pa.table({n: rows[:, i] for i, n in enumerate(names)}), tmp_path / "log.parquet")
    robot = w.robot_type("(2,0)")
    a = cli.read_log(tmp_path / "log.parquet", robot)
    b = I.read_log(_write(tmp_path / "log.csv", ",".join(names), rows), robot)
    for x, y in zip(a[1:], b[1:]):
        np.testing.assert_array_equal(x, y)
    pq.write_table(pa.table({n: rows[:, i] for i, n in enumerate(names[:-1])}), tmp_path / "short.parquet")
    with pytest.raises(ValueError, match=r"missing column\(s\) \['u2'\]"):
        cli.read_log(tmp_path / "short.parquet", robot)
