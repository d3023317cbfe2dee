"""The shared command-line layer (wmrjax.cli): the persistent compilation cache (in subprocesses: it is
global JAX configuration, which the library itself never touches), how a failed run ends (a bad
option: exit 2 with the usage; an error of the work: exit 1, its traceback under --verbose), and one
writer per output directory."""

import json
import os
import signal
import subprocess
import sys
import time
from pathlib import Path

import pytest

SCRIPT = """
import sys, jax
from wmrjax.cli import machine, options
p = options.parser("x", None)
a = p.parse_args(sys.argv[1:])
print(machine.use_compilation_cache(a), jax.config.jax_compilation_cache_dir,
      jax.config.jax_persistent_cache_min_compile_time_secs)
"""


def _run(*argv):
    return subprocess.run(
        [sys.executable, "-c", SCRIPT, *argv], capture_output=True, text=True, check=True
    ).stdout.split()


def test_compilation_cache_on_by_default_off_on_request(tmp_path):
    d = tmp_path / "cache"
    assert _run("--compile-cache", str(d)) == [str(d), str(d), "0.0"]
    assert d.is_dir()
    assert _run("--compile-cache", str(d), "--no-compile-cache")[:2] == ["None", "None"]


def test_library_import_leaves_the_cache_alone():
    out = subprocess.run(
        [sys.executable, "-c", "import jax, wmrjax; print(jax.config.jax_compilation_cache_dir)"],
        capture_output=True,
        text=True,
        check=True,
    ).stdout.strip()
    assert out == "None"


# --- exit statuses ---------------------------------------------------------------------------------


def test_an_error_of_the_work_exits_1_without_the_usage(tmp_path, capsys, monkeypatch):
    """A ValueError raised inside the work (here section 6.1's run, after its options passed) is an
    error of the work, not a bad option: exit 1 and ``PROG: error: MESSAGE`` without the usage text,
    its traceback printed only with --verbose. (It was exit 2 with the usage, as if an option were
    wrong, and a bug's traceback was lost.)"""
    from paper import section_6_1

    def run(*args, **kwargs):
        raise ValueError("the work went wrong")

    monkeypatch.setattr(section_6_1, "run", run)
    for verbose in (False, True):
        with pytest.raises(SystemExit) as exc:
            section_6_1.main(["--out", str(tmp_path), "--no-compile-cache"] + ["--verbose"] * verbose)
        assert exc.value.code == 1
        err = capsys.readouterr().err
        last = err.strip().splitlines()[-1]
        assert "usage:" not in err and ": error: the work went wrong" in last, err
        assert ("Traceback (most recent call last)" in err) == verbose, err
        assert ('raise ValueError("the work went wrong")' in err) == verbose, err
        assert ("--verbose" in last) == (not verbose), last


def test_a_bad_option_still_exits_2_with_the_usage(tmp_path, capsys):
    from paper import section_6_1

    for argv in (["--dt", "0"], ["--dt", "20"]):  # argparse's own check; a cross-option check
        with pytest.raises(SystemExit) as exc:
            section_6_1.main(argv + ["--out", str(tmp_path), "--no-compile-cache"])
        assert exc.value.code == 2
        err = capsys.readouterr().err
        assert err.startswith("usage: ") and ": error: " in err.strip().splitlines()[-1], err


# --- one writer per output directory (real concurrent processes) ------------------------------

ROOT = Path(__file__).resolve().parent.parent
HOLDER = """
import sys, time
from wmrjax import _files as files
files.acquire_output(sys.argv[1], "holder of the test")
print("locked", flush=True)
time.sleep(120)
"""
SWEEP = """
title = "lock"
[controller]
law = "dynamic"
robot = "(2,0)"
[reference]
family = "circle"
[initial]
space = "output"
x = [-0.5, 0.5]
[simulation]
t_final = 1.0
dt = 0.02
"""


def _env():
    env = dict(os.environ, PYTHONPATH=str(ROOT))
    env.pop("WMRJAX_OUTPUT_LOCK", None)
    return env


def test_a_second_writer_is_refused_and_a_dead_ones_lock_taken_over(tmp_path):
    """A live process holds --out: a sweep into it exits 2 naming that process (pid, command);
    killed with -9, its lock is stale: the next writer names it, takes it over, and removes the
    temporary files a killed atomic write left (in --out and below)."""
    from wmrjax import _files as files

    holder = subprocess.Popen(
        [sys.executable, "-c", HOLDER, str(tmp_path)], stdout=subprocess.PIPE, text=True, env=_env()
    )
    try:
        assert holder.stdout.readline().strip() == "locked"
        spec = tmp_path / "s.toml"
        spec.write_text(SWEEP)
        r = subprocess.run(
            [sys.executable, "-m", "wmrjax", "sweep", str(spec), "--out", str(tmp_path)],
            capture_output=True,
            text=True,
            env=_env(),
            cwd=ROOT,
            timeout=300,
        )
        assert r.returncode == 2
        assert f"being written by another run: process {holder.pid}" in r.stderr and "holder of the test" in r.stderr
        assert not (tmp_path / "runs.parquet").exists()
    finally:
        holder.send_signal(signal.SIGKILL)
        holder.wait()
    (tmp_path / "blocks").mkdir()
    torn = [tmp_path / ".runs.parquet.x1.wmrjax-tmp", tmp_path / "blocks" / ".block_000000.npz.x2.wmrjax-tmp"]
    for f in torn:
        f.write_bytes(b"half")
    # a user's own temporary files, and one behind a link to a directory elsewhere, are not ours
    (tmp_path / "deep").mkdir()
    elsewhere = tmp_path.parent / f"{tmp_path.name}-elsewhere"
    elsewhere.mkdir(exist_ok=True)
    theirs = [tmp_path / ".x.tmp", tmp_path / "deep" / ".report.tmp", elsewhere / ".runs.parquet.x3.wmrjax-tmp"]
    for f in theirs:
        f.write_bytes(b"keep")
    (tmp_path / "link").symlink_to(elsewhere, target_is_directory=True)
    taker = subprocess.run(
        [
            sys.executable,
            "-c",
            "import sys; from wmrjax import _files as files; print(files.acquire_output(sys.argv[1], 'taker'))",
            str(tmp_path),
        ],
        capture_output=True,
        text=True,
        env=_env(),
        timeout=120,
    )
    assert taker.returncode == 0, taker.stderr
    assert f"removed the stale lock of process {holder.pid} ('holder of the test'" in taker.stderr
    assert not any(f.exists() for f in torn)
    assert all(f.read_bytes() == b"keep" for f in theirs)
    assert json.loads((tmp_path / files.LOCK_NAME).read_text())["command"] == "taker"


def test_two_sweeps_into_one_directory(tmp_path):
    """Two different sweeps started together into one --out: one runs to the end, the other is
    refused (exit 2) while the first holds the directory; the table is the first's alone and its
    lock is gone afterwards. (Both used to exit 0 with rows of one under the other's labels.)"""
    from wmrjax import _files as files

    out = tmp_path / "out"
    specs = []
    for poles in (1.0, 2.0):
        specs.append(tmp_path / f"s{poles}.toml")
        specs[-1].write_text(SWEEP + f"[gains]\npoles = {poles}\n")
    cmd = [sys.executable, "-m", "wmrjax", "sweep", "--out", str(out), "--no-compile-cache"]
    first = subprocess.Popen(
        cmd + [str(specs[0])], stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True, env=_env(), cwd=ROOT
    )
    for _ in range(600):
        if (out / files.LOCK_NAME).exists():
            break
        time.sleep(0.1)
    second = subprocess.run(cmd + [str(specs[1])], capture_output=True, text=True, env=_env(), cwd=ROOT, timeout=300)
    _, err = first.communicate(timeout=600)
    assert first.returncode == 0, err[-2000:]
    assert second.returncode == 2 and f"process {first.pid}" in second.stderr
    s = json.loads((out / "summary.json").read_text())
    assert s["problem"]["gains"]["poles"] == 1.0
    assert not (out / files.LOCK_NAME).exists()


def test_the_command_lines_say_which_extra_they_need():
    """Without the cli extra a job is refused before it starts, naming what to install, instead
    of computing and then failing on an import when it writes its figures; ``wmrjax --help``
    still lists the jobs."""
    block = "import sys; sys.modules['pyarrow'] = None; from wmrjax.cli import main; "
    done = subprocess.run(
        [sys.executable, "-c", block + "sys.exit(main(['certify', '--help']))"],
        capture_output=True,
        text=True,
        cwd=ROOT,
    )
    assert done.returncode != 0
    assert 'pip install "wmrjax[cli]"' in done.stderr and "pyarrow" in done.stderr
    listed = subprocess.run(
        [sys.executable, "-c", block + "sys.exit(main(['--help']))"], capture_output=True, text=True, cwd=ROOT
    )
    assert listed.returncode == 0 and "certify" in listed.stdout and "sweep" in listed.stdout, listed
