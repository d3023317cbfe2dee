"""Helpers of the probe's driver snippets: cases that start real processes of the tree under
test (concurrent writers, killed runs, resumed runs) and report facts for the oracle.

Every process started here runs ``python ARGV...`` with this process's environment (the tree
first on ``PYTHONPATH``, the run's compilation cache) in the current directory; its output
goes to files, so that two concurrent processes never block on a pipe.
"""

import itertools
import json
import os
import shutil
import signal
import subprocess
import sys
import time

_ids = itertools.count()


class Proc:
    """A started process and where its output goes."""

    def __init__(self, argv, name=None):
        self.name = name or f"p{next(_ids)}"
        self.out = open(f".{self.name}.out", "w")
        self.err = open(f".{self.name}.err", "w")
        self.t0 = time.monotonic()
        self.popen = subprocess.Popen([sys.executable, *argv], stdout=self.out, stderr=self.err)

    @property
    def pid(self) -> int:
        """The process id."""
        return self.popen.pid

    def finish(self, timeout=None) -> dict:
        """Wait for the process: its exit status, seconds and the tail of its stderr."""
        try:
            rc = self.popen.wait(timeout=timeout)
        except subprocess.TimeoutExpired:
            self.popen.kill()
            rc = None
            self.popen.wait()
        seconds = time.monotonic() - self.t0
        self.out.close()
        self.err.close()
        with open(f".{self.name}.err", errors="replace") as f:
            err = f.read()
        lines = [x for x in err.splitlines() if x.strip()]
        return {
            "rc": rc,
            "seconds": round(seconds, 2),
            "err": err[-1500:],
            "last": lines[-1] if lines else "",
            "traceback": "Traceback (most recent call last)" in err,
        }


def start(*argv, name=None) -> Proc:
    """Start ``python ARGV...``."""
    return Proc(argv, name)


def run(*argv, timeout=None) -> dict:
    """Run ``python ARGV...`` to its end (see :meth:`Proc.finish`)."""
    return start(*argv).finish(timeout)


def wait_for(path, timeout=120.0, poll=0.05) -> bool:
    """Wait until ``path`` exists; False after ``timeout`` seconds."""
    t0 = time.monotonic()
    while time.monotonic() - t0 < timeout:
        if os.path.exists(path):
            return True
        time.sleep(poll)
    return False


def children(pid: int) -> list:
    """The process ids of the children of ``pid`` (Linux)."""
    try:
        with open(f"/proc/{pid}/task/{pid}/children") as f:
            return [int(x) for x in f.read().split()]
    except OSError:
        return []


def kill9(pid: int) -> None:
    """kill -9 of one process."""
    try:
        os.kill(pid, signal.SIGKILL)
    except ProcessLookupError:
        pass


def same_table(a, b):
    """Whether two Parquet tables are equal (None when one is missing or unreadable)."""
    try:
        import pyarrow.parquet as pq

        return bool(pq.read_table(a).equals(pq.read_table(b)))
    except Exception:  # noqa: BLE001 - a missing or torn table is reported as None
        return None


def rows(path):
    """The number of rows of a Parquet table (None when missing or unreadable)."""
    try:
        import pyarrow.parquet as pq

        return pq.read_metadata(path).num_rows
    except Exception:  # noqa: BLE001
        return None


def read_json(path):
    """A JSON file's content, or None."""
    try:
        with open(path) as f:
            return json.load(f)
    except (OSError, ValueError):
        return None


def copytree(a, b) -> None:
    """Copy a directory, leaving out the writer's lock."""
    shutil.copytree(a, b, ignore=shutil.ignore_patterns(".wmrjax-*"))


def same_output(out, ref, kind: str):
    """Whether the output directory ``out`` holds what ``ref`` (the same command run alone)
    holds: for a sweep its table and summary counts, for a tuning its gains and held-out loss."""
    a, b = read_json(f"{out}/summary.json") or {}, read_json(f"{ref}/summary.json") or {}
    if kind == "sweep":
        return bool(
            same_table(f"{out}/runs.parquet", f"{ref}/runs.parquet")
            and a.get("counts") == b.get("counts")
            and a.get("fingerprint") == b.get("fingerprint")
        )
    return bool(
        read_json(f"{out}/gains.json") == read_json(f"{ref}/gains.json")
        and a.get("tuned_gains") == b.get("tuned_gains")
        and a.get("heldout_loss") == b.get("heldout_loss")
    )


def finished(spec: str, out: str, command: tuple = ("wmrjax", "sweep")) -> dict:
    """``python -m wmrjax JOB SPEC --out OUT`` as if just run: the first time in a probe run it runs
    into the run's fixture directory (``$PROBE_FIXTURES``), later it is a copy of that output
    (without the writer's lock); returns the run's facts (see :meth:`Proc.finish`)."""
    import hashlib

    with open(spec, "rb") as f:
        key = hashlib.sha256(" ".join(command).encode() + f.read()).hexdigest()[:16]
    root = os.environ.get("PROBE_FIXTURES")
    if not root:
        return run("-m", *command, spec, "--out", out)
    cached = os.path.join(root, key)
    facts = read_json(cached + ".json")
    if facts is None:
        shutil.rmtree(cached, ignore_errors=True)
        facts = run("-m", *command, spec, "--out", cached)
        with open(cached + ".json", "w") as f:
            json.dump(facts, f)
    copytree(cached, out)
    return facts
