"""Every job's ``summary.json`` before and after a change: each job runs on the same problem in an
old checkout (its own command lines) and in this one, and every value is compared, timings
aside (issue 55: the package moved, the answers must not).

    git worktree add /tmp/old REV
    python -m benchmarks.same_summaries --old /tmp/old --old-rev REV --out results/same_summaries

The old checkout is imported first on ``PYTHONPATH`` (this checkout's virtual environment runs
both); an old checkout with the ``wmrjax`` command already (no ``experiments/`` folder) runs the
new command lines too. Prints one table (job, values compared, identical, differing, the differing keys) and
writes it with every difference to ``OUT/summary.json``.
"""

from __future__ import annotations

import argparse
import json
import math
import os
import re
import subprocess
import sys
import time
from pathlib import Path

ROOT = Path(__file__).resolve().parent.parent

# job -> (old command after ``python -m``, new one): the S-path problem with its own settings
JOBS = {
    "sweep": (
        ["experiments.sweep", "experiments/problems/s_path.toml"],
        ["wmrjax", "sweep", "wmrjax/examples/s_path.toml"],
    ),
    "tune": (["tuning", "experiments/problems/s_path.toml"], ["wmrjax", "tune", "wmrjax/examples/s_path.toml"]),
    "certify": (
        ["experiments.certify", "experiments/problems/s_path.toml"],
        ["wmrjax", "certify", "wmrjax/examples/s_path.toml"],
    ),
    "identify": (
        ["experiments.identify", "experiments/problems/car_waypoints.toml", "--log", "LOG"],
        ["wmrjax", "identify", "wmrjax/examples/car_waypoints.toml", "--log", "LOG"],
    ),
    "export": (
        ["experiments.export", "experiments/problems/s_path.toml"],
        ["wmrjax", "export", "wmrjax/examples/s_path.toml"],
    ),
}

# a key that measures time or the machine, not the answer
TIMING = re.compile(r"wall|time|_s$|seconds|elapsed|throughput|first_calls|stages|timing|compile|heartbeat|memory|rss")


def car_log(path: Path) -> Path:
    """A 10 s, 50 Hz log of the shipped (1,1) car (L = 0.33 m, torque level) integrated by SciPy
    (the tests' oracle), with 5 % geometry and input-scale errors and sensor noise, as CSV."""
    sys.path.insert(0, str(ROOT / "tests"))  # the oracle is the tests' own SciPy integration
    from identify_oracle import make_log  # noqa: E402 -- found through the line above

    noise = [0.01, 0.01, 0.005, 0.005]
    log = make_log(
        "(1,1)", "torque", L=0.33, geometry_scale=1.05, input_scale=[0.95, 1.0], noise_std=noise, n=501,
        period=0.02, seed=4,
    )  # fmt: skip
    rows = [[*map(float, (t, *x, *u))] for t, x, u in zip(log.t, log.posture, log.command)]
    lines = ["t,x,y,theta,beta1,u1,u2"] + [",".join(repr(v) for v in r) for r in rows]
    path.parent.mkdir(parents=True, exist_ok=True)
    path.write_text("\n".join(lines) + "\n")
    return path


def _run(tree: Path, argv: list, out: Path) -> float:
    """``python -m ARGV --out OUT`` in ``tree`` with ``tree`` first on the path; its wall time [s]."""
    env = dict(os.environ, PYTHONPATH=str(tree))
    t0 = time.perf_counter()
    r = subprocess.run(
        [sys.executable, "-m", *argv, "--out", str(out), "--no-compile-cache"],
        cwd=tree,
        env=env,
        capture_output=True,
        text=True,
    )
    # 1: certify's alarms (the files are written; compared like any value), never a traceback
    if r.returncode not in (0, 1) or "Traceback (most recent call last)" in r.stderr:
        raise RuntimeError(f"{' '.join(argv)} in {tree} failed ({r.returncode}):\n{r.stderr[-3000:]}")
    return time.perf_counter() - t0


def flatten(x, prefix: str = "") -> dict:
    """Dotted key -> leaf value of a JSON tree (list items by index)."""
    if isinstance(x, dict):
        return {k: v for key, val in x.items() for k, v in flatten(val, f"{prefix}{key}.").items()}
    if isinstance(x, list):
        return {k: v for i, val in enumerate(x) for k, v in flatten(val, f"{prefix}{i}.").items()}
    return {prefix.rstrip("."): x}


def _normalise(v, trees: dict):
    """A value with the checkouts' and output directories' names replaced (paths moved, not answers)."""
    if not isinstance(v, str):
        return v
    for old, new in trees.items():
        v = v.replace(old, new)
    return v.replace("experiments/problems/", "wmrjax/examples/").replace("experiments/sweeps/", "wmrjax/examples/")


def _same(a, b) -> bool:
    if isinstance(a, float) and isinstance(b, float) and math.isnan(a) and math.isnan(b):
        return True
    return a == b


def compare(old: dict, new: dict, trees: dict) -> dict:
    """Every non-timing value of two summaries: counts and the keys that differ or exist in one only."""
    fo, fn = flatten(old), flatten(new)
    keys = sorted(k for k in set(fo) | set(fn) if not TIMING.search(k))
    differ = [k for k in keys if k in fo and k in fn and not _same(_normalise(fo[k], trees), _normalise(fn[k], trees))]
    only = [k for k in keys if (k in fo) != (k in fn)]
    return {
        "compared": len(keys),
        "identical": len(keys) - len(differ) - len(only),
        "differ": differ,
        "only_in_one": only,
    }


def main(argv=None) -> int:
    p = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    p.add_argument("--old", type=Path, required=True, help="the old checkout (a git worktree)")
    p.add_argument("--old-rev", default="?", help="its commit, for the record")
    p.add_argument("--out", type=Path, default=ROOT / "results" / "same_summaries")
    p.add_argument("--jobs", nargs="+", default=list(JOBS), choices=list(JOBS))
    a = p.parse_args(argv)
    a.out.mkdir(parents=True, exist_ok=True)
    rows = {}
    log = str(car_log(a.out.resolve() / "car_log.csv"))
    for job in a.jobs:
        old_argv, new_argv = ([log if x == "LOG" else x for x in argv] for argv in JOBS[job])
        if not (a.old / "experiments").is_dir():  # the old checkout has the one command already
            old_argv = new_argv
        outs = {"old": (a.out / job / "old").resolve(), "new": (a.out / job / "new").resolve()}
        walls = {"old": _run(a.old.resolve(), old_argv, outs["old"]), "new": _run(ROOT, new_argv, outs["new"])}
        trees = {str(a.old.resolve()): str(ROOT), str(outs["old"]): str(outs["new"])}
        s_old, s_new = (json.loads((outs[k] / "summary.json").read_text()) for k in ("old", "new"))
        rows[job] = compare(s_old, s_new, trees) | {"wall_s": walls, "command": " ".join(new_argv)}
        r = rows[job]
        print(
            f"{job}: {r['identical']} of {r['compared']} identical; differ {r['differ']}; in one only {r['only_in_one']}"
        )
    print("\n| job | values compared (timings aside) | identical | differing |\n|---|---|---|---|")
    for job, r in rows.items():
        print(
            f"| `{r['command']}` | {r['compared']} | {r['identical']} | {', '.join(r['differ'] + r['only_in_one']) or 'none'} |"
        )
    (a.out / "summary.json").write_text(json.dumps({"old_rev": a.old_rev, "jobs": rows}, indent=1))
    return 0


if __name__ == "__main__":
    sys.exit(main())
