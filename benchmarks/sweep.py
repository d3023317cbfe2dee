"""Scale of the sweep runner: a sweep of ``--runs`` runs of the §6.1 loop (a square grid of
initial position errors, 10 s, dt = 0.01 s) with 1 and with 2 processes, and a sweep killed
at 50 % and resumed.

    python -m benchmarks.sweep --out results/sweep_benchmark

Each sweep runs as its own ``wmrjax sweep`` process (as a user runs it), so
the peak resident memory is that of its process tree (``getrusage`` of the children in a
fresh parent; with 2 processes, the largest of them). Writes ``summary.json``: wall time, throughput in runs/s
and trajectory-steps/s, peak memory, and the time to finish a sweep killed half way.
"""

from __future__ import annotations

import math
import os
import signal
import subprocess
import sys
import time
from pathlib import Path

from wmrjax import _files as files
from wmrjax.cli import machine, options

PEAK_OF = Path(__file__).resolve().parent / "peak_of.py"  # a process tree's peak memory, run by path

SPEC = """title = "scale benchmark: the section 6.1 loop over {n} x {n} initial position errors"
[controller]
law = "dynamic"
robot = "(2,0)"
level = "velocity"
[geometry]
e = 0.0
[reference]
family = "paper_62"
[initial]
space = "output"
x = {{ min = -12.0, max = 12.0, num = {n} }}
y = {{ min = -12.0, max = 12.0, num = {n} }}
[gains]
poles = 1.0
[simulation]
t_final = 10.0
dt = 0.01
block = {block}
"""


def _sweep(spec: Path, out: Path, extra=(), kill_at: float | None = None, n_blocks: int = 0) -> dict:
    """Run one sweep process tree; returns wall time, peak RSS [bytes] and whether it was killed."""
    rss = out.parent / f".{out.name}.maxrss"
    cmd = [sys.executable, "-m", "wmrjax", "sweep", str(spec), "--out", str(out), *extra]
    t0 = time.perf_counter()
    proc = subprocess.Popen(
        # a fresh parent per sweep (benchmarks/peak_of.py), so the peak is this sweep's tree alone
        [sys.executable, str(PEAK_OF), str(rss), *cmd],
        stderr=subprocess.PIPE,
        text=True,
        start_new_session=True,
    )
    killed = False
    if kill_at is not None:
        while proc.poll() is None:
            done = len(list((out / "blocks").glob("block_*.npz"))) if (out / "blocks").exists() else 0
            if done >= kill_at * n_blocks:
                os.killpg(proc.pid, signal.SIGKILL)  # the whole tree, as a kill -9 would
                killed = True
                break
            time.sleep(0.2)
    _, err = proc.communicate()
    wall = time.perf_counter() - t0
    if proc.returncode and not killed:
        raise RuntimeError(f"{' '.join(cmd)} failed:\n{err[-3000:]}")
    peak = int(rss.read_text()) * 1024 if rss.exists() and not killed else None  # Linux: ru_maxrss in KiB
    return {"wall_s": wall, "peak_rss_bytes": peak, "killed": killed}


def run(out: Path, runs: int, block: int, progress=print) -> dict:
    import json

    n = int(math.isqrt(runs))
    spec = out / "scale.toml"
    spec.write_text(SPEC.format(n=n, block=block))
    total = n * n
    n_blocks = -(-total // block)
    steps = total * 1000
    res = {"runs": total, "grid": [n, n], "steps_per_run": 1000, "block": block, "cpu_count": os.cpu_count()}
    for label, extra in (("one_process", ()), ("two_processes", ("--processes", "2"))):
        progress(f"{label}: {total} runs")
        r = _sweep(spec, out / label, ("--fresh", *extra))
        s = json.loads((out / label / "summary.json").read_text())
        r |= {
            "throughput_runs_per_s": total / r["wall_s"],
            "throughput_trajectory_steps_per_s": steps / r["wall_s"],
            "compute_wall_s": s["execution"]["compute_wall_s"],
            "compute_throughput_trajectory_steps_per_s": s["execution"]["throughput_trajectory_steps_per_s"],
            "counts": s["counts"],
        }
        res[label] = r
    progress("killed at 50 %, then resumed")
    killed = _sweep(spec, out / "resumed", ("--fresh",), kill_at=0.5, n_blocks=n_blocks)
    done = len(list((out / "resumed" / "blocks").glob("block_*.npz")))
    resumed = _sweep(spec, out / "resumed")
    import pyarrow.parquet as pq

    same = pq.read_table(out / "resumed" / "runs.parquet").equals(pq.read_table(out / "one_process" / "runs.parquet"))
    res["resume"] = {
        "killed_after_s": killed["wall_s"],
        "blocks_done_at_kill": done,
        "blocks": n_blocks,
        "resume_wall_s": resumed["wall_s"],
        "same_table_as_uninterrupted": bool(same),
    }
    res["same_table_one_and_two_processes"] = bool(
        pq.read_table(out / "two_processes" / "runs.parquet").equals(
            pq.read_table(out / "one_process" / "runs.parquet")
        )
    )
    files.write_json(out / "summary.json", res)
    return res


def main(argv=None) -> int:
    from wmrjax.cli import running

    p = options.parser(__doc__.splitlines()[0], "results/sweep_benchmark")
    p.add_argument(
        "--runs", type=options.count, default=1_000_000, help="runs per sweep (rounded down to a square grid)"
    )
    p.add_argument("--block", type=options.count, default=1024, help="runs per block")
    a = p.parse_args(argv)
    machine.configure_xla()  # before JAX starts its backend
    running.prepare_output(p, a.out)
    res = run(a.out, a.runs, a.block)
    one, two = res["one_process"], res["two_processes"]
    print(
        f"{res['runs']} runs: 1 process {one['wall_s']:.0f} s ({one['throughput_runs_per_s']:.0f} runs/s, peak "
        f"{(one['peak_rss_bytes'] or 0) / 1e9:.2f} GB); 2 processes {two['wall_s']:.0f} s; resume after a kill at "
        f"{res['resume']['blocks_done_at_kill']}/{res['resume']['blocks']} blocks: {res['resume']['resume_wall_s']:.0f} s"
    )
    return 0


if __name__ == "__main__":
    sys.exit(main())
