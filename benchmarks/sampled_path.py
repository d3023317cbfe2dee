"""A sampled path's load time and memory against its number of samples (issue 57 item 3: the
spline's collocation system is banded and solved block by block, in time and memory linear in
the samples).

    python -m benchmarks.sampled_path [--record]

Per row, in a fresh process (so that its peak resident memory is the load's own and its time
includes compiling): samples of a circle of radius 2 m at 0.5 rad/s every 0.01 s,
``wmrjax.references.from_samples`` of degree 5 (the velocity-level laws' spline) and 7 (the
torque-level (1,1) law's), then one position evaluated mid-path (the pieces are ready). Reports
the wall seconds of the load, the process's peak resident memory and the position's distance
to the circle.
Writes ``sampled_path.json`` into ``--out`` and prints the table; ``--record``: the page's record too
(``benchmarks/records/sampled_path.json``, rendered into docs/benchmarks.md by :mod:`benchmarks.page`).
"""

from __future__ import annotations

import argparse
import json
import resource
import subprocess
import sys
import time
from pathlib import Path

import jax
import numpy as np

from benchmarks import page
from wmrjax import references as R
from wmrjax.cli import machine

jax.config.update("jax_enable_x64", True)
ROOT = Path(__file__).resolve().parent.parent
SIZES = (1_000, 10_000, 100_000, 1_000_000)


def load_one(n: int, degree: int) -> dict:
    """One load in this process (called in a fresh one): seconds, peak RSS, the path's error."""
    t = np.arange(n) * 0.01
    xy = np.stack([2.0 * np.cos(0.5 * t), 2.0 * np.sin(0.5 * t)], 1)
    t0 = time.perf_counter()
    ref = R.from_samples(t, xy, degree=degree)
    mid = 0.5 * t[-1]
    p = np.asarray(ref.position(mid))
    seconds = time.perf_counter() - t0
    return {
        "samples": n,
        "degree": degree,
        "load_s": seconds,
        "peak_rss_bytes": resource.getrusage(resource.RUSAGE_SELF).ru_maxrss * 1024,
        "position_error_m": float(abs(np.hypot(*p) - 2.0)),
    }


def main(argv=None) -> int:
    p = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    p.add_argument("--out", type=Path, default=ROOT / "results" / "benchmarks" / "sampled_path")
    p.add_argument(
        "--record", action="store_true", help="write the page's record (benchmarks/records/sampled_path.json)"
    )
    p.add_argument("--one", nargs=2, type=int, help=argparse.SUPPRESS)  # the fresh process: samples, degree
    a = p.parse_args(argv)
    machine.configure_xla()  # the command lines' XLA:CPU settings (the children inherit them), before JAX starts
    if a.one:
        print(json.dumps(load_one(*a.one)))
        return 0
    rows = []
    for n in SIZES:
        for degree in (5, 7):
            r = subprocess.run(
                [sys.executable, "-m", "benchmarks.sampled_path", "--one", str(n), str(degree)],
                cwd=ROOT,
                capture_output=True,
                text=True,
            )
            if r.returncode:
                rows.append({"samples": n, "degree": degree, "error": (r.stderr.strip().splitlines() or ["?"])[-1]})
            else:
                rows.append(json.loads(r.stdout.strip().splitlines()[-1]))
            print(page.sampled_path({"rows": rows[-1:]}).splitlines()[-1], flush=True)
    print(page.sampled_path({"rows": rows}))
    page.save(
        "sampled_path", a.out, record_too=a.record, command="python -m benchmarks.sampled_path --record", rows=rows
    )
    return 0


if __name__ == "__main__":
    sys.exit(main())
