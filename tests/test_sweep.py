"""The sweep file and its runner: every bad key refused before compiling, the table against
direct simulations, a killed sweep resumed to the same table, 2 processes giving the same
table as 1, and the shipped sweep files valid."""

import json
import os
import subprocess
import sys
from pathlib import Path

import jax
import jax.numpy as jnp
import numpy as np
import pyarrow.parquet as pq
import pytest

import wmrjax as w
from wmrjax import references as R
from wmrjax.cli import sweep as sweep_cli
from wmrjax.sweep import run as sweep_run
from wmrjax.sweep import spec as S

ROOT = Path(__file__).resolve().parents[1]

TINY = """
title = "tiny"
[controller]
law = "dynamic"
robot = "(2,0)"
level = "velocity"
[geometry]
e = 0.0
[reference]
family = "circle"
options = { radius = [2.0, 3.0], omega = 0.5 }
[initial]
space = "output"
x = [-0.5, 0.0, 0.7]
y = { min = -1.0, max = 1.0, num = 3 }
[gains]
poles = 1.0
[simulation]
t_final = 2.0
dt = 0.02
block = 4
"""


def _write(tmp_path, text, name="s.toml"):
    p = tmp_path / name
    p.write_text(text)
    return p


def _table(path):
    t = pq.read_table(path)
    return {n: t.column(n).to_numpy(zero_copy_only=False) for n in t.column_names}


@pytest.fixture(scope="module")
def cache(tmp_path_factory):
    """A persistent compilation cache shared by this module's sweeps (a rerun loads the compiled
    rollout, as a user's resumed sweep does)."""
    return str(tmp_path_factory.mktemp("xla_cache"))


@pytest.fixture(scope="module")
def tiny(tmp_path_factory, cache):
    """The tiny sweep run once in this process: (spec path, output directory)."""
    d = tmp_path_factory.mktemp("sweep")
    spec = _write(d, TINY)
    assert sweep_cli.main([str(spec), "--out", str(d / "out"), "--compile-cache", cache]) == 0
    return spec, d / "out"


def test_table_matches_direct_simulations(tiny):
    spec, out = tiny
    t = _table(out / "runs.parquet")
    assert len(t["run"]) == 2 * 3 * 3 and list(t["run"]) == list(range(18))
    for col in (
        "reference_radius",
        "initial_error_x",
        "initial_error_y",
        "failed",
        "t_failure",
        "min_margin",
        "final_position_error",
        "final_heading_error",
        "min_distance",
        "outcome",
    ):
        assert col in t
    ctrl = w.dynamic_linearization("(2,0)", "velocity")
    for i in (0, 7, 17):
        ref = R.circle(radius=t["reference_radius"][i], omega=0.5)
        params = ctrl.params(ref, poles=1.0, geometry=w.Geometry(e=0.0))
        zeta = ctrl.reference_jet(0.0, params)[:2]
        zeta = zeta.at[0].add(jnp.array([t["initial_error_x"][i], t["initial_error_y"][i]]))
        tr = w.simulate(ctrl, ctrl.initial_state(zeta, params), params, dt=0.02, n_steps=100, save_every=5)
        post = ref.posture(jnp.asarray(2.0))
        np.testing.assert_allclose(
            t["final_position_error"][i], float(jnp.linalg.norm(tr.final_state[:2] - post[:2])), rtol=1e-12
        )
        np.testing.assert_allclose(t["min_margin"][i], float(tr.diagnostics.min_margin), rtol=1e-12)
        dist = jax.vmap(lambda z: ctrl.singular_distance(ctrl.psi(z, params), params))(tr.state)
        np.testing.assert_allclose(t["min_distance"][i], float(jnp.min(dist)), rtol=1e-12)
    # the grid, last axis fastest: radius, then x, then y
    np.testing.assert_array_equal(t["reference_radius"][:9], 2.0)
    np.testing.assert_array_equal(t["initial_error_y"][:3], [-1.0, 0.0, 1.0])
    np.testing.assert_array_equal(t["initial_error_x"][:9:3], [-0.5, 0.0, 0.7])
    s = json.loads((out / "summary.json").read_text())
    assert s["runs"] == 18 and sum(s["counts"].values()) == 18
    assert s["counts"]["converged"] == int(np.sum(t["outcome"] == "converged"))
    assert s["execution"]["blocks"] == 5 and s["execution"]["runs_computed"] == 18
    assert set(s["swept"]) == {"reference_radius", "initial_error_x", "initial_error_y"}
    assert "map_initial_error_x_initial_error_y.png" in s["figures"]
    assert (out / "map_initial_error_x_initial_error_y.png").stat().st_size > 10_000


def test_the_library_sweep_is_the_command_line_s(tiny, cache, tmp_path):
    """wmrjax.sweep.sweep (one process, from Python) writes the table and summary the command line
    wrote, and returns them as a typed report whose summary is the file."""
    from wmrjax.problem import Problem
    from wmrjax.sweep import SweepReport, sweep

    spec, out = tiny
    r = sweep(Problem.load(spec), tmp_path / "lib", source=str(spec), progress=lambda m: None)
    assert isinstance(r, SweepReport) and r.table == tmp_path / "lib" / "runs.parquet"
    on_disk = json.loads((tmp_path / "lib" / "summary.json").read_text())
    assert json.loads(json.dumps(r.summary())) == on_disk
    cli = json.loads((out / "summary.json").read_text())
    timing = ("execution", "wall_time_s")
    assert {k: v for k, v in on_disk.items() if k not in timing} == {k: v for k, v in cli.items() if k not in timing}
    assert r.counts == cli["counts"] and r.execution["runs_computed"] == 18
    a, b = _table(r.table), _table(out / "runs.parquet")
    assert a.keys() == b.keys()
    for k in a:
        np.testing.assert_array_equal(a[k], b[k], err_msg=k)  # bit for bit (NaN where NaN)


def test_killed_sweep_resumes_to_the_same_table(tiny, cache, tmp_path, monkeypatch):
    spec, out = tiny
    done = []
    original = sweep_run.Progress.update

    def dies_after_first(self, runs, blocks):
        original(self, runs, blocks)
        done.append(blocks)
        raise KeyboardInterrupt  # killed after the first call (one block per device)

    monkeypatch.setattr(sweep_run.Progress, "update", dies_after_first)
    with pytest.raises(SystemExit) as stopped:  # Ctrl-C: status 130 and one line, no traceback
        sweep_cli.main([str(spec), "--out", str(tmp_path), "--compile-cache", cache])
    assert stopped.value.code == 130
    finished = len(list((tmp_path / "blocks").glob("block_*.npz")))
    assert finished == done[0] < 5
    monkeypatch.setattr(sweep_run.Progress, "update", original)
    assert sweep_cli.main([str(spec), "--out", str(tmp_path), "--compile-cache", cache]) == 0
    s = json.loads((tmp_path / "summary.json").read_text())
    assert s["execution"]["runs_resumed"] == 4 * finished and s["execution"]["runs_computed"] == 18 - 4 * finished
    assert pq.read_table(tmp_path / "runs.parquet").equals(pq.read_table(out / "runs.parquet"))
    # another sweep file in the same directory is refused, not mixed in
    other = _write(tmp_path, TINY.replace("poles = 1.0", "poles = 2.0"), "other.toml")
    with pytest.raises(SystemExit):
        sweep_cli.main([str(other), "--out", str(tmp_path), "--no-compile-cache"])


def test_foreign_and_torn_blocks_are_named_and_recomputed(tiny, cache, tmp_path, capsys):
    """A block file of another sweep (its fingerprint rewritten), one moved to another place,
    and a truncated one are each named and recomputed, giving the same table; assembling them
    directly is refused. Before: a foreign block was assembled silently (its rows under this
    sweep's labels) and a truncated one raised a raw zipfile.BadZipFile naming no block."""
    import shutil

    spec, out = tiny
    shutil.copytree(out, tmp_path / "o", ignore=shutil.ignore_patterns(".wmrjax-*"))
    o = tmp_path / "o"
    plan = S.load(spec)
    with np.load(sweep_run.block_path(o, 0)) as f:
        d = dict(f)
    np.savez(sweep_run.block_path(o, 0), **{**d, "fingerprint": np.str_("0123456789abcdef")})
    shutil.copy(sweep_run.block_path(o, 3), sweep_run.block_path(o, 1))  # block 3's rows as block 1
    data = sweep_run.block_path(o, 2).read_bytes()
    sweep_run.block_path(o, 2).write_bytes(data[: len(data) // 2])  # a torn write
    with pytest.raises(ValueError, match="block_000000.npz belongs to another sweep"):
        sweep_run.assemble(plan, o)
    assert sweep_cli.main([str(spec), "--out", str(o), "--compile-cache", cache]) == 0
    err = capsys.readouterr().err
    assert "block_000000.npz belongs to another sweep" in err
    assert "block_000001.npz holds block 3" in err and "block_000002.npz is torn" in err
    assert pq.read_table(o / "runs.parquet").equals(pq.read_table(out / "runs.parquet"))
    s = json.loads((o / "summary.json").read_text())
    assert s["execution"]["runs_computed"] == 12  # the three bad blocks of 4 runs each
    (o / sweep_run.STATE_FILE).write_text("{not json")
    with pytest.raises(SystemExit):  # corrupt state: refused, naming the way out
        sweep_cli.main([str(spec), "--out", str(o), "--compile-cache", cache])
    assert "sweep_state.json is not valid JSON" in capsys.readouterr().err
    assert sweep_cli.main([str(spec), "--out", str(o), "--compile-cache", cache, "--fresh"]) == 0


def test_two_processes_give_the_same_table(tiny, cache, tmp_path):
    spec, out = tiny
    env = dict(os.environ, PYTHONPATH=str(ROOT))
    r = subprocess.run(
        [
            sys.executable,
            "-m",
            "wmrjax",
            "sweep",
            str(spec),
            "--out",
            str(tmp_path),
            "--processes",
            "2",
            "--compile-cache",
            cache,
        ],
        cwd=ROOT,
        env=env,
        capture_output=True,
        text=True,
        timeout=600,
    )
    assert r.returncode == 0, r.stderr[-3000:]
    assert "[process 1]" in r.stderr and "[process 0]" in r.stderr
    s = json.loads((tmp_path / "summary.json").read_text())
    assert s["execution"]["processes"] == 2
    assert pq.read_table(tmp_path / "runs.parquet").equals(pq.read_table(out / "runs.parquet"))


BAD = [
    ("[controller]\nlaw = 'dynamic'\nrobot = '(2,0)'\ncolour = 1", r"\[controller\]: unknown key\(s\) \['colour'\]"),
    ("[controllr]\nlaw = 'dynamic'", r"unknown section\(s\) \['controllr'\]"),
    ("[controller]\nlaw = 'adaptive'\nrobot = '(2,0)'", r"\[controller\] law: expected one of \['dynamic', 'static'\]"),
    (
        "[controller]\nlaw = 'dynamic'\nrobot = '(3,0)'",
        r"no dynamic linearizing law \(Table 4\) for type\(s\) \['\(3,0\)'\]",
    ),
    ("[controller]\nlaw = 'dynamic'\nrobot = '(2,0)'\nlevel = 'jerk'", r"\[controller\] level: expected one of"),
    ("[geometry]\ne = []", r"\[geometry\] e: an empty list"),
    ("[geometry]\ne = 'zero'", r"\[geometry\] e: expected a number, a list of numbers"),
    ("[geometry]\ne = { min = 0.0, max = 1.0 }", r"\[geometry\] e: a grid table needs exactly min, max, num"),
    ("[initial]\nx = { min = 1.0, max = 0.0, num = 3 }", r"\[initial\] x: max must be > min"),
    (
        "[initial]\nx = { low = -1.0, high = 1.0 }",
        r"\[initial\] x: a \{ low, high \} range needs random = \{ count, seed \}",
    ),
    ("[initial]\nrandom = { count = 0 }", r"\[initial.random\] count: expected an integer >= 1"),
    ("[initial]\ntheta = 0.1", r"\[initial\]: unknown key\(s\) \['theta'\]"),
    ("[simulation]\nt_final = 2.0\ndt = 0.03", r"t_final = 2.0 s is not a whole number of steps"),
    ("[simulation]\nt_final = -2.0\ndt = 0.02", r"\[simulation\] t_final: expected a number > 0"),
    ("[gains]\npoles = [1.0, -1.0]", r"\[gains\] poles: values must be > 0"),
    ("[gains]\nomega = 2.0", r"\[gains\]: give either poles, or omega and zeta"),
    ("[gains]\nfile = 'missing.json'", r"\[gains\] file '.*missing.json': not a regular file"),
    ("[plant]\ninput_limit = [1.0, 2.0, 3.0]", r"\[plant\] input_limit: expected a list of 2 numbers"),
    ("[plant]\ninput_limit = [1.0, 0.0]", r"\[plant\] input_limit: values must be > 0"),
    ("[reference]\nfamily = 'spiral'", r"\[reference\] family: expected one of"),
    (
        "[reference]\nfamily = 'circle'\noptions = { radius = 2.0, speed = 1.0 }",
        r"\[reference.options\]: unknown key\(s\) \['speed'\]",
    ),
    ("[reference]\nfamily = 'samples'\nfile = 'nope.csv'", r"\[reference\] file '.*nope.csv': not a regular file"),
    # combinations the paper excludes
    (
        "[reference]\nfamily = 'paper_66'\n[simulation]\nt_final = 12.0\ndt = 0.02",
        r"\[reference\] paper_66 .* reaches the singular set .* at t = 9.99 s",
    ),
    ("[controller]\nlaw = 'dynamic'\nrobot = '(1,1)'\n[geometry]\nL = 0.0", r"\[geometry\] for type \(1,1\): .*L"),
    (
        "[controller]\nlaw = 'static'\nrobot = '(2,0)'\n[geometry]\ne = 0.0\n[initial]\nspace = 'physical'",
        r"\[geometry\] for type \(2,0\): .*e",
    ),
    (
        "[controller]\nlaw = 'static'\nrobot = '(2,0)'\n[geometry]\ne = 0.3",
        r"space = \"output\" .* needs a dynamic law",
    ),
    ("[simulation]\nt_final = 2.0\ndt = 3.5", r"not a whole number of steps"),
]


def _spec(fragment: str) -> str:
    """TINY with the sections named in ``fragment`` replaced by it."""
    sections = {}
    current = None
    for line in (TINY + "\n" + fragment).splitlines():
        if line.startswith("["):
            current = line.split("]")[0].strip("[")
            sections[current] = []
        elif current is not None:
            sections[current].append(line)
    keep = TINY.split("[controller]")[0]
    return keep + "\n".join(f"[{k}]\n" + "\n".join(v) for k, v in sections.items())


@pytest.mark.parametrize("fragment, match", BAD)
def test_bad_sweep_files_are_refused_before_compiling(fragment, match, tmp_path, monkeypatch):
    calls = []
    monkeypatch.setattr(jax.lax, "scan", lambda *a, **k: calls.append("scan"))
    with pytest.raises(S.SpecError, match=match):
        S.load(_write(tmp_path, _spec(fragment)))
    assert not calls


def test_cli_refuses_bad_files_and_options(tmp_path, capsys):
    with pytest.raises(SystemExit) as e:
        sweep_cli.main([str(tmp_path / "none.toml")])
    assert e.value.code == 2 and "not found" in capsys.readouterr().err
    bad = _write(tmp_path, "[controller\nlaw=")
    with pytest.raises(SystemExit):
        sweep_cli.main([str(bad), "--out", str(tmp_path / "o")])
    assert "not valid TOML" in capsys.readouterr().err
    with pytest.raises(SystemExit):
        sweep_cli.main([str(bad), "--process-id", "1"])
    assert "need --coordinator" in capsys.readouterr().err


@pytest.mark.parametrize("name", ["section_6_1_position_grid", "random_references", "sampled_lane_change"])
def test_shipped_sweeps_are_valid(name):
    plan = S.load(ROOT / "wmrjax" / "examples" / f"{name}.toml")
    expect = {
        "section_6_1_position_grid": 81 * 81,
        "random_references": 8 * 32 * 32,
        "sampled_lane_change": 2 * 2 * 21 * 21,
    }
    assert plan.n_runs == expect[name]


def test_sweep_options_documented_and_output_checked(tmp_path, capsys):
    p = sweep_cli.parser()
    for action in p._actions:
        if action.option_strings and action.dest != "help":
            assert action.help and len(action.help) > 8, action.option_strings
    spec = _write(tmp_path, TINY)
    f = tmp_path / "a_file"
    f.write_text("x")
    with pytest.raises(SystemExit):
        sweep_cli.main([str(spec), "--out", str(f)])
    assert "exists and is not a directory" in capsys.readouterr().err
    with pytest.raises(SystemExit):
        sweep_cli.main([str(spec), "--out", str(tmp_path / "o"), "--processes", "0"])
    assert "argument --processes" in capsys.readouterr().err
    # more processes or host devices than cores (--devices 4096 ran 8x slower) are refused
    cores = os.cpu_count() or 1
    for opt in ("--processes", "--devices"):
        with pytest.raises(SystemExit):
            sweep_cli.main([str(spec), "--out", str(tmp_path / "o"), opt, str(cores + 1)])
        assert f"{opt} {cores + 1} is more than this machine's {cores} cores" in capsys.readouterr().err
    # a block larger than the group is the group (it padded every call to the block: 1e7 runs for 18)
    big = _write(tmp_path, TINY.replace("block = 4", "block = 10000000"), "big.toml")
    assert S.load(big).block == 18


def test_a_dead_worker_stops_the_others(tiny, cache, tmp_path):
    """kill -9 of one of two worker processes: the launcher stops the other within seconds,
    names the dead one and says how to resume (before: the other waited 96 s at the barrier and
    aborted with a C++ stack dump); the same command then resumes to the same table."""
    import signal
    import time

    spec, out = tiny
    slow = _write(
        tmp_path, TINY.replace("t_final = 2.0", "t_final = 40.0").replace("block = 4", "block = 1"), "slow.toml"
    )
    env = dict(os.environ, PYTHONPATH=str(ROOT))
    cmd = [
        sys.executable,
        "-m",
        "wmrjax",
        "sweep",
        str(slow),
        "--out",
        str(tmp_path / "o"),
        "--processes",
        "2",
        "--compile-cache",
        cache,
    ]
    launcher = subprocess.Popen(cmd, cwd=ROOT, env=env, stderr=subprocess.PIPE, text=True)
    children = Path(f"/proc/{launcher.pid}/task/{launcher.pid}/children")
    t0 = time.monotonic()
    while time.monotonic() - t0 < 120 and not (tmp_path / "o" / "blocks").exists():
        time.sleep(0.2)  # the workers have started computing
    pids = [int(x) for x in children.read_text().split()]
    assert len(pids) == 2
    os.kill(pids[1], signal.SIGKILL)
    killed = time.monotonic()
    _, err = launcher.communicate(timeout=120)
    assert launcher.returncode != 0
    assert time.monotonic() - killed < 30, err[-2000:]
    assert "process 1 of 2 failed" in err and "run the same command again to resume" in err
    r = subprocess.run(cmd, cwd=ROOT, env=env, capture_output=True, text=True, timeout=600)
    assert r.returncode == 0, r.stderr[-3000:]


STATIC = """
[controller]
law = "static"
robot = "(2,0)"
level = "torque"
task = "point"
[geometry]
e = 0.3
delta = 1.5707963267948966
[reference]
family = "circle"
[initial]
space = "physical"
random = { count = 3, seed = 7 }
x = { low = -0.2, high = 0.2 }
theta = 0.0
[gains]
poles = 1.0
[simulation]
t_final = 1.0
dt = 0.02
"""


def test_static_physical_sweep_starts_on_the_reference_and_draws_reproducibly(tmp_path, cache):
    """Physical-space initial errors for a static torque-level law: the tracked point starts at the
    reference's plus (x, y), its output velocity equal to the reference's (so a zero error stays
    zero: exact linearization), and the random draws follow numpy's Generator(seed), key by key."""
    zero = _write(
        tmp_path,
        STATIC.replace("random = { count = 3, seed = 7 }\nx = { low = -0.2, high = 0.2 }", "x = [0.0, 0.2]"),
        "zero.toml",
    )
    assert sweep_cli.main([str(zero), "--out", str(tmp_path / "zero"), "--compile-cache", cache]) == 0
    t = _table(tmp_path / "zero" / "runs.parquet")
    assert t["final_position_error"][0] < 1e-8  # on the reference from the start, and stays there (RK4: 1.6e-9)
    assert t["final_position_error"][1] > 1e-3  # 0.2 m off: decays like (1 + t) e^-t, still 0.15 m at 1 s
    np.testing.assert_allclose(t["final_position_error"][1], 0.2 * 2 * np.exp(-1.0), rtol=1e-6)
    rnd = _write(tmp_path, STATIC, "random.toml")
    plan = S.load(rnd)
    rng = np.random.default_rng(7)
    x = rng.uniform(-0.2, 0.2, 3)
    cols = S.columns_of(plan.groups[0], S.unravel(plan.groups[0], 0, 3))
    np.testing.assert_array_equal(cols["initial_error_x"], x)
    np.testing.assert_array_equal(cols["initial_error_theta"], 0.0)
    assert plan.swept == ["initial_error_x"]


def test_histogram_of_a_constant_margin():
    """A static point law's |det K| = |e sin(delta)| is the same for every run up to its last bits:
    numpy's 50 bins over a range of 1e-16 raised 'Too many bins' and the sweep wrote no summary."""
    from wmrjax.sweep.report import _hist_args

    x = np.log10(np.full(10, 0.3 * np.sin(1.2))) + np.r_[np.zeros(9), 1e-16]
    with pytest.raises(ValueError, match="Too many bins"):
        np.histogram(x, bins=50)
    counts, edges = np.histogram(*_hist_args(x))
    assert counts.tolist() == [10] and edges[0] < x.min() <= x.max() < edges[1]
    assert _hist_args(np.arange(5.0))[1] == 50


def test_a_directory_where_the_sweep_writes_a_file_is_refused_by_name(tmp_path):
    """A directory named like the state file or a block (the probe of #34: a raw IsADirectoryError
    traceback) is refused naming it, and left in place: it is not the sweep's to remove."""
    from wmrjax.sweep import run as sweep_run

    (tmp_path / sweep_run.STATE_FILE).mkdir()
    with pytest.raises(ValueError, match=r"sweep_state.json is not a regular file"):
        sweep_run.read_state(tmp_path)
    with pytest.raises(ValueError, match=r"sweep_state.json is not a regular file"):
        sweep_run.prepare(None, tmp_path, fresh=True)
    sweep_run.block_path(tmp_path, 1).mkdir(parents=True)
    with pytest.raises(ValueError, match=r"block_000001.npz is not a regular file"):
        sweep_run.block_done(None, tmp_path, 1)
    assert sweep_run.block_path(tmp_path, 1).is_dir()
