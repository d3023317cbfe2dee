"""Nothing written outside ``--out``, nothing deleted that a job did not write, nothing run from
the user's files, messages that quote at most an excerpt of a file, sizes estimated before
allocation (issue 57: the second reliability probe's bad cases). Each test failed on the code
before the fix (said per test)."""

import json
import os
import signal
import subprocess
import sys
import time
from pathlib import Path

import jax
import jax.numpy as jnp
import numpy as np
import pytest

from wmrjax import _files as files
from wmrjax import io
from wmrjax import references as R
from wmrjax.export import check as export_check
from wmrjax.problem import CASE_NAME_MAX, Problem, ProblemError
from wmrjax.sweep.report import file_part

PROBLEM = """
[controller]
law = "dynamic"
robot = "(2,0)"
[reference]
family = "circle"
[initial]
x = {{ min = -0.1, max = 0.1, num = 2 }}
[simulation]
t_final = 1.0
dt = 0.01
[[case]]
name = {name}
"""


@pytest.mark.parametrize(
    "name",
    [
        "a/../../../X/Y",  # before: a sweep wrote a PNG outside --out
        "../escape",
        ".hidden",
        "tab\there",
        "new\nline",
        "x" * (CASE_NAME_MAX + 1),
        "",
        "a\\b",
    ],
)
def test_case_names_are_labels_not_paths(tmp_path, name):
    f = tmp_path / "p.toml"
    f.write_text(PROBLEM.format(name=json.dumps(name)))
    with pytest.raises(ProblemError, match=r"\[\[case\]\] #1 name: expected a label of 1 to 64") as err:
        Problem.load(f)
    assert len(str(err.value)) < 400  # a long name is quoted as an excerpt


def test_good_case_names_load_and_stay_file_names(tmp_path):
    f = tmp_path / "p.toml"
    f.write_text(PROBLEM.format(name=json.dumps("tuned v2+noise_0.1")))
    assert [n for n, _ in Problem.load(f).cases()] == ["tuned v2+noise_0.1"]
    assert file_part("tuned v2+noise_0.1") == "tuned_v2+noise_0.1"
    assert "/" not in file_part("a/../../b") and not file_part("../x").startswith(".")


def test_atomic_write_replaces_a_link_and_never_writes_through_it(tmp_path):
    target = tmp_path / "outside.txt"
    target.write_text("the user's")
    out = tmp_path / "out"
    out.mkdir()
    (out / "step.c").symlink_to(target)
    files.write_bytes(out / "step.c", b"generated")
    assert target.read_text() == "the user's"
    assert not (out / "step.c").is_symlink() and (out / "step.c").read_bytes() == b"generated"
    assert [p.name for p in out.iterdir()] == ["step.c"]  # no temporary file left


def test_artifact_reload_imports_nothing_from_the_output_directory(tmp_path):
    """Before: the fresh process ran with its working directory at --out, so a json.py lying
    there was imported (and run) in place of the standard library's."""
    marker = tmp_path / "ran"
    (tmp_path / "json.py").write_text(f"open({str(marker)!r}, 'w').write('ran')\n")
    (tmp_path / "numpy.py").write_text(f"open({str(marker)!r}, 'w').write('ran')\n")

    def step(t, m, s):
        return 2.0 * m, s + t, jnp.sum(m)

    args = (jnp.zeros(()), jnp.zeros(2), jnp.zeros(1))
    art = tmp_path / "step.jax_export"
    art.write_bytes(jax.export.export(jax.jit(step))(*args).serialize())

    class Run:
        t = np.array([0.0, 0.1])
        measured = np.array([[1.0, 2.0], [3.0, 4.0]])
        initial_state = np.zeros(1)

    got = export_check.reload_in_fresh_process(art, Run(), tmp_path)
    assert not marker.exists()
    np.testing.assert_allclose(got["command"], [[2.0, 4.0], [6.0, 8.0]])
    assert got["wmrjax_imported"] is False


def test_a_secret_file_is_never_quoted():
    """Before: a samples 'file' that is /proc/self/environ printed the whole environment."""
    os.environ["WMRJAX_TEST_SECRET"] = "hunter2-secret-value"
    try:
        with pytest.raises(ValueError) as err:
            io.read_csv_columns("/proc/self/environ", ("t", "x", "y"), "reference samples")
    finally:
        del os.environ["WMRJAX_TEST_SECRET"]
    assert "hunter2" not in str(err.value) and "NUL bytes" in str(err.value)
    assert len(str(err.value)) < 200


def test_a_huge_header_gives_a_short_message(tmp_path):
    """Before: a 5 MB header line gave a 5 MB message."""
    f = tmp_path / "wide.csv"
    f.write_text("t," + "q" * 5_000_000 + "\n0,1\n")
    with pytest.raises(ValueError, match=r"header line has 5000002 characters") as err:
        io.read_csv_columns(f, ("t", "x", "y"), "reference samples")
    assert len(str(err.value)) < 300
    g = tmp_path / "many.csv"
    g.write_text(",".join(f"c{'z' * 40}{i}" for i in range(50)) + "\n" + ",".join(["1"] * 50) + "\n")
    with pytest.raises(ValueError, match=r"missing column\(s\) \['t', 'x', 'y'\].*\.\.\. \(50 columns\)") as err:
        io.read_csv_columns(g, ("t", "x", "y"), "reference samples")
    assert len(str(err.value)) < 600


def test_extra_text_columns_are_ignored_and_bad_values_named(tmp_path):
    """The docs say other columns are ignored: before, a text column refused the whole file."""
    f = tmp_path / "labelled.csv"
    f.write_text("t,x,y,label\n0,1,2,start\n1,2,3,end of the lane\n")
    got = io.read_csv_columns(f, ("t", "x", "y"), "samples")
    np.testing.assert_array_equal(got["x"], [1.0, 2.0])
    f.write_text("t,x,y\n0,1,2\n1," + "9" * 30 + "abc,3\n")
    with pytest.raises(ValueError, match=r"data row 2, column 'x': '9+\.*'?.*is not a number") as err:
        io.read_csv_columns(f, ("t", "x", "y"), "samples")
    assert len(str(err.value)) < 200
    f.write_text("t,x,y\n0,1,2\n1,2\n")
    with pytest.raises(ValueError, match="data row 2 has 2 values; every row needs 3"):
        io.read_csv_columns(f, ("t", "x", "y"), "samples")


def test_a_huge_sampled_path_is_refused_before_allocation(monkeypatch):
    """Before: 10^6 samples ended in a raw RESOURCE_EXHAUSTED after minutes (a dense solve of 24 TB).
    The banded solve takes them in 4 s and 1.2 GB (docs/problem_files.md); a path whose spline
    does not fit in the memory available (here 100 MB) is still refused at once, with its size and
    the fix, before anything is allocated."""
    monkeypatch.setattr(R.resources, "available_bytes", lambda: 100 * 10**6)
    t = np.arange(1_000_000.0) * 0.01
    with pytest.raises(ValueError, match=r"sampled path of 1000000 samples .* needs about 1.7 GB.*resample"):
        R.from_samples(t, np.c_[t, np.zeros_like(t)])


def test_torn_write_cleanup_keeps_user_files_in_process(tmp_path):
    """Before: acquiring --out removed every '.*.tmp' anywhere under it (rglob)."""
    user = [tmp_path / ".x.tmp", tmp_path / "deep" / ".report.tmp"]
    user[1].parent.mkdir()
    for f in user:
        f.write_text("mine")
    ours = tmp_path / f".summary.json.abc{files.TMP_SUFFIX}"
    ours.write_text("half")
    token = files.acquire_output(tmp_path, "test")
    try:
        assert all(f.read_text() == "mine" for f in user) and not ours.exists()
    finally:
        files.release_output(tmp_path, token)


def test_one_directory_holds_one_jobs_results(tmp_path):
    """Before: a certification into a finished sweep's --out (directly or through a link) exited 0
    and replaced the sweep's summary.json beside its table."""
    files.claim_output(tmp_path, "wmrjax sweep")
    files.claim_output(tmp_path, "wmrjax sweep")  # the same job again (a rerun, a resume)
    with pytest.raises(files.OutputLocked, match=r"holds the results of 'wmrjax sweep', not of 'wmrjax cert"):
        files.claim_output(tmp_path, "wmrjax certify")
    link = tmp_path.parent / f"{tmp_path.name}-link"
    link.symlink_to(tmp_path, target_is_directory=True)
    with pytest.raises(files.OutputLocked, match="one directory holds one job's results"):
        files.claim_output(link, "wmrjax certify")


def test_fresh_removes_only_the_files_the_other_job_recorded(tmp_path, monkeypatch):
    """Before: --fresh did not exist for another job's output (the refusal said to choose another
    directory). Now it removes the files that job recorded writing, and nothing else: not the
    user's own files beside them, nothing through a link, nothing outside --out, whatever the
    manifest says."""
    monkeypatch.setattr(files, "_RECORDING", [])
    out, outside = tmp_path / "out", tmp_path / "outside.json"
    outside.write_text("keep")
    files.claim_output(out, "wmrjax sweep")
    files.record_writes(out)
    files.write_json(out / "summary.json", {"a": 1})
    files.write_bytes(out / "maps" / "x.png", b"png")
    files.write_json(out / "summary.json", {"a": 2})  # written twice, recorded twice
    files.write_bytes(tmp_path / "elsewhere.bin", b"not under out: not recorded")
    (out / "mine.txt").write_text("the user's")
    (out / "maps" / "mine.csv").write_text("the user's")
    (out / "link.json").symlink_to(outside)
    manifest = out / f"{files.MANIFEST_PREFIX}{os.getpid()}"
    lines = manifest.read_text().splitlines()
    assert lines == ["summary.json", "maps/x.png", "summary.json"]
    with open(manifest, "a") as fh:  # an edited manifest: a link, a way out, an absolute path
        fh.write(f"link.json\n../outside.json\n{outside}\nmaps/../../outside.json\n")
    with pytest.raises(files.OutputLocked, match="rerun with --fresh to remove them"):
        files.claim_output(out, "wmrjax certify")
    removed = files.claim_output(out, "wmrjax certify", fresh=True)
    assert removed == ["summary.json", "maps/x.png"]
    assert outside.read_text() == "keep" and (out / "link.json").is_symlink()
    assert (out / "mine.txt").exists() and (out / "maps" / "mine.csv").exists()
    assert (tmp_path / "elsewhere.bin").exists() and not manifest.exists()
    assert json.loads((out / files.JOB_NAME).read_text()) == {"job": "wmrjax certify"}
    files.claim_output(out, "wmrjax certify")  # now this job's directory
    # a directory the removed files leave empty goes too
    files.write_bytes(out / "deep" / "er" / "y.png", b"png")
    assert files.claim_output(out, "wmrjax export", fresh=True) == ["deep/er/y.png"]
    assert not (out / "deep").exists()


def test_fresh_on_the_command_line_replaces_another_jobs_results(tmp_path):
    """The command line: a certification into a directory holding an export's results is refused
    and names --fresh; with --fresh it runs, the export's recorded files gone, the user's kept."""
    out = tmp_path / "out"
    files.claim_output(out, "wmrjax export")
    (out / "wmr.c").write_text("old code")
    (out / f"{files.MANIFEST_PREFIX}1").write_text("wmr.c\n")
    (out / "notes.md").write_text("mine")
    problem = tmp_path / "p.toml"
    problem.write_text(
        PROBLEM.split("[[case]]")[0].replace("{{", "{").replace("}}", "}")
        + "[certify]\nn_empirical = 8\nn_directions = 2\nn_starts = 0\nmap_grid = 3\n"
    )
    cmd = [sys.executable, "-m", "wmrjax", "certify", str(problem), "--out", str(out)]
    refused = subprocess.run(cmd, capture_output=True, text=True, timeout=600)
    assert refused.returncode == 2 and "rerun with --fresh" in refused.stderr, refused.stderr[-2000:]
    done = subprocess.run(cmd + ["--fresh"], capture_output=True, text=True, timeout=600)
    assert done.returncode == 0, done.stderr[-2000:]
    assert "--fresh removed 1 files of another job's results" in done.stderr
    assert not (out / "wmr.c").exists() and (out / "notes.md").read_text() == "mine"
    assert json.loads((out / "summary.json").read_text())["experiment"] == "certify"
    recorded = {line for m in out.glob(files.MANIFEST_PREFIX + "*") for line in m.read_text().splitlines()}
    assert {"summary.json", "slice_map.png"} <= recorded


@pytest.mark.skipif(not sys.platform.startswith("linux"), reason="PR_SET_PDEATHSIG is Linux's")
def test_a_killed_launchers_workers_die_with_it():
    """Before: killing the launcher of `sweep --processes 2` orphaned its workers, which kept
    computing and later overwrote the next command's runs.parquet and summary.json."""
    launcher = subprocess.Popen(
        [
            sys.executable,
            "-c",
            "import subprocess, sys, time\n"
            "from wmrjax.cli.launch import die_with_parent\n"
            "w = subprocess.Popen([sys.executable, '-c', 'import time; time.sleep(60)'], preexec_fn=die_with_parent)\n"
            "print(w.pid, flush=True)\n"
            "time.sleep(60)\n",
        ],
        stdout=subprocess.PIPE,
        text=True,
    )
    worker = int(launcher.stdout.readline())
    launcher.send_signal(signal.SIGKILL)
    launcher.wait()
    for _ in range(100):  # the worker is a zombie of init until reaped: gone or dead state
        try:
            state = Path(f"/proc/{worker}/stat").read_text().split(")")[-1].split()[0]
        except FileNotFoundError:
            return
        if state in ("Z", "X"):
            return
        time.sleep(0.05)
    os.kill(worker, signal.SIGKILL)
    pytest.fail(f"worker {worker} outlived its launcher by 5 s")


def test_a_resumed_run_sees_a_changed_path_file(tmp_path):
    """Before: the tuner's checkpoint fingerprint hashed the sections as written (the CSV's name),
    so a run resumed after the path file's content changed, mixing steps on two paths."""
    t = np.linspace(0.0, 10.0, 21)
    (tmp_path / "path.csv").write_text("t,x,y\n" + "".join(f"{a},{a},{0.1 * a}\n" for a in t))
    text = PROBLEM.split("[[case]]")[0].replace('family = "circle"', 'family = "samples"\nfile = "path.csv"')
    (tmp_path / "p.toml").write_text(text.replace("{{", "{").replace("}}", "}"))
    first = Problem.load(tmp_path / "p.toml").setting("tuning")
    (tmp_path / "path.csv").write_text("t,x,y\n" + "".join(f"{a},{a},{0.2 * a}\n" for a in t))
    second = Problem.load(tmp_path / "p.toml").setting("tuning")
    assert first.data == second.data  # what the old fingerprint hashed
    assert first.content_digest() != second.content_digest()
    assert Problem.load(tmp_path / "p.toml").setting("tuning").content_digest() == second.content_digest()


def test_the_exported_step_flags_times_outside_its_sampled_path():
    """Before (the reliability probe): the exported step of a path sampled on [0, 4] s extrapolated
    silently past it (0.2 m off at 8 s, 10.9 m at 12 s); the span was in neither the header nor
    the summary."""
    import wmrjax as w
    from wmrjax import export as X

    t = np.linspace(0.0, 4.0, 41)
    ctrl = w.dynamic_linearization("(2,0)")
    params = ctrl.params(R.from_samples(t, np.c_[t, 0.2 * np.sin(t)]), poles=1.0, geometry=w.Geometry(e=0.2))
    step = X.control_step(ctrl, params)
    assert step.span == (0.0, 4.0)
    z0 = ctrl.reference_state(0.0, params)
    state = step.initial_state(0.0, z0[3:])
    fn = jax.jit(step.fn)
    regs = [float(fn(jnp.asarray(s), z0[:3], state)[2]) for s in (0.0, 2.0, 4.0, 4.5, -0.5)]
    assert all(abs(r) > 1e-3 for r in regs[:3]) and regs[3:] == [0.0, 0.0]
    assert "valid for t in [0.0, 4.0] s" in X.generate_c(step)[f"{step.name}.h"]
    circle = ctrl.params(R.circle(), poles=1.0, geometry=w.Geometry(e=0.2))
    assert X.control_step(ctrl, circle).span is None


@pytest.mark.parametrize("t_final, dt", [(1e308, 0.01), (10.0, 1e-300)])
def test_overflowing_horizons_are_refused_by_name(tmp_path, t_final, dt):
    """Before: t_final = 1e308 or dt = 1e-300 ended in a raw OverflowError (int of an infinite
    step count) or a run that could not end."""
    text = (
        PROBLEM.split("[[case]]")[0]
        .replace("t_final = 1.0", f"t_final = {t_final!r}")
        .replace("dt = 0.01", f"dt = {dt!r}")
    )
    (tmp_path / "p.toml").write_text(text.replace("{{", "{").replace("}}", "}"))
    with pytest.raises(ProblemError, match=r"\[simulation\] t_final / dt = .* steps, more than 1e\+12"):
        Problem.load(tmp_path / "p.toml").setting("sweep")


def test_ctrl_c_leaves_a_resumable_sweep_and_one_line(tmp_path):
    """Before: Ctrl-C during a sweep printed a traceback, or, when Python raised it inside one of
    jaxlib's garbage-collection callbacks, was dropped and the sweep ran on to status 0. Now:
    exit 130, one line saying what is kept, and the same command finishes from the kept blocks."""
    spec = tmp_path / "s.toml"
    spec.write_text(
        PROBLEM.split("[[case]]")[0]
        .replace("{{ min = -0.1, max = 0.1, num = 2 }}", "{{ min = -0.3, max = 0.3, num = 16000 }}")
        .replace("t_final = 1.0", "t_final = 20.0")
        .replace("{{", "{")
        .replace("}}", "}")
        + "block = 256\n"
    )
    cmd = [sys.executable, "-m", "wmrjax", "sweep", str(spec), "--out", str(tmp_path / "out")]
    proc = subprocess.Popen(cmd, stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True)
    blocks = tmp_path / "out" / "blocks"
    for _ in range(1200):  # interrupt once the first blocks are kept
        if (blocks.is_dir() and any(blocks.glob("block_*.npz"))) or proc.poll() is not None:
            break
        time.sleep(0.05)
    proc.send_signal(signal.SIGINT)
    out, err = proc.communicate(timeout=300)
    assert proc.returncode == 130, err[-2000:]
    assert "interrupted; what finished is kept in" in err and "Traceback" not in err
    again = subprocess.run(cmd, capture_output=True, text=True, timeout=600)
    assert again.returncode == 0, again.stderr[-2000:]
    assert "16000 runs" in again.stdout
