"""The sweep's command line: one process, ``--processes N`` local processes, or one process of
a multi-host run (``--coordinator HOST:PORT --process-id I --num-processes N``)."""

from __future__ import annotations

import json
import os
import signal
import socket
import subprocess
import sys
import time
from pathlib import Path

import jax

from wmrjax import _files as files
from wmrjax.cli import common, options
from wmrjax.problem import CASE_NAME, Problem, ProblemError
from wmrjax.sweep import report, run
from wmrjax.sweep import spec as S

DOC = """Run a sweep file: a controller over robots, references, initial conditions, gains and
actuator limits. Writes DIR/runs.parquet (one row per run), DIR/summary.json and PNG maps.
A killed sweep resumes from its finished blocks when rerun with the same file and --out."""


def parser():

    p = common.parser(DOC, default_out=None)
    p.add_argument(
        "spec",
        type=options.problem_file,
        help="the problem file to sweep (TOML; see docs/problem_files.md), or a shipped example",
    )
    options.add_set(p)
    p.add_argument("--out", type=Path, default=None, help="output directory (default: results/sweeps/<spec name>)")
    p.add_argument("--fresh", action="store_true", help="discard finished blocks of an earlier run in --out")
    p.add_argument(
        "--gains",
        type=Path,
        nargs="+",
        default=None,
        help="tuned-gains files (gains.json of wmrjax tune): the sweep runs the file's own gains as case "
        "'default' and each file as a case of its own ('tuned', or the file's directory name)",
    )
    p.add_argument(
        "--processes",
        type=options.count,
        default=1,
        help="local processes joined by jax.distributed, each computing its share of the blocks",
    )
    p.add_argument(
        "--devices",
        type=options.count,
        default=None,
        help="JAX host devices per process (default: the cores divided among the processes)",
    )
    p.add_argument("--coordinator", default=None, help="HOST:PORT of process 0, for a run over several hosts")
    p.add_argument(
        "--process-id", type=options.nonnegative_int, default=None, help="this process's index (with --coordinator)"
    )
    p.add_argument("--num-processes", type=options.count, default=None, help="number of processes (with --coordinator)")
    return p


def main(argv=None) -> int:
    p = parser()
    a = p.parse_args(argv)

    distributed = a.coordinator is not None
    if distributed and (a.process_id is None or a.num_processes is None):
        options.fail(p, "--coordinator needs --process-id and --num-processes")
    if not distributed and (a.process_id is not None or a.num_processes is not None):
        options.fail(p, "--process-id and --num-processes need --coordinator HOST:PORT")
    if distributed and a.process_id >= a.num_processes:
        options.fail(p, f"--process-id {a.process_id} must be < --num-processes {a.num_processes}")
    if distributed and a.processes != 1:
        options.fail(p, "--processes starts local processes itself; do not combine it with --coordinator")
    if not a.spec.is_file():
        options.fail(p, f"sweep file {str(a.spec)!r} not found")
    if a.out is None:
        a.out = Path("results") / "sweeps" / a.spec.stem
    n_proc = a.num_processes if distributed else a.processes
    cores = os.cpu_count() or 1
    # more processes or host devices than cores run no faster (many more run much slower) and
    # each process holds its own JAX (about 0.6 GB)
    if a.processes > cores:
        options.fail(p, f"--processes {a.processes} is more than this machine's {cores} cores")
    if a.devices is not None and a.devices > cores:
        options.fail(
            p, f"--devices {a.devices} is more than this machine's {cores} cores (JAX host devices run one per core)"
        )
    devices = a.devices or max(1, cores // n_proc)
    options.configure_xla(devices)  # before JAX starts its backend
    # one writer per --out: the launching process (its workers inherit the lock's token), or
    # process 0 of a run over several hosts
    options.prepare_output(p, a.out, lock=not distributed or a.process_id == 0)
    try:
        with options.reliable_interrupt():
            if a.processes > 1:
                return _launch(p, a, devices)
            return _run(p, a, a.process_id or 0, a.num_processes or 1)
    except ValueError as err:  # raised by the work (the file and --out were checked before it): exit 1
        options.fail_work(p, str(err), verbose=a.verbose)
    except KeyboardInterrupt:  # Ctrl-C: the finished blocks are kept, one line instead of a traceback
        options.interrupted(p, a.out)


def problem_of(a):
    """The sweep file's problem, paired with ``--gains`` files as cases (``default`` and one per file)."""

    problem = options.with_set(Problem.load(a.spec), a)
    if not a.gains:
        return problem
    if "case" in problem.data:
        raise ProblemError(
            "--gains pairs the file's own gains with tuned ones as [[case]]s; this file has [[case]]s "
            "already: add the tuned gains there"
        )
    names = ["tuned"] if len(a.gains) == 1 else [f.resolve().parent.name for f in a.gains]
    if len(set(names)) != len(names) or not all(CASE_NAME.fullmatch(n) for n in names):
        names = [f"tuned_{i + 1}" for i in range(len(a.gains))]
    cases = [{"name": "default"}] + [{"name": n, "gains": {"file": str(f.resolve())}} for n, f in zip(names, a.gains)]
    return problem.with_values({"case": cases})


def _launch(p, a, devices: int) -> int:
    """Start ``--processes`` local processes (jax.distributed over 127.0.0.1) and wait for them."""

    common.enable_x64()

    try:  # refuse a bad file or another sweep's --out here, before starting anything
        plan = S.plan(problem_of(a))
        run.check_memory(plan, devices, a.processes)
        run.prepare(plan, a.out, a.fresh)
    except ValueError as err:
        options.fail(p, str(err))
    with socket.socket() as s:
        s.bind(("127.0.0.1", 0))
        port = s.getsockname()[1]
    base = [
        sys.executable,
        "-m",
        "wmrjax",
        "sweep",
        str(a.spec),
        "--out",
        str(a.out),
        "--devices",
        str(devices),
        "--coordinator",
        f"127.0.0.1:{port}",
        "--num-processes",
        str(a.processes),
    ]
    if a.gains:
        base += ["--gains", *[str(f) for f in a.gains]]
    if a.no_compile_cache:
        base.append("--no-compile-cache")
    elif a.compile_cache is not None:
        base += ["--compile-cache", str(a.compile_cache)]
    procs = [subprocess.Popen(base + ["--process-id", str(i)], preexec_fn=die_with_parent) for i in range(a.processes)]
    try:
        return _wait(procs, a)
    except BaseException:  # Ctrl-C or a kill of the launcher: its workers do not outlive it
        for pr in procs:
            if pr.poll() is None:
                pr.terminate()
        raise


def die_with_parent() -> None:
    """In a worker, before it runs: ask Linux to send it SIGTERM when its launcher dies (even by
    SIGKILL), so that no orphan keeps computing and later overwrites the next command's table
    and summary under a lock it no longer has. Elsewhere a no-op (the launcher still stops
    its workers on any exception)."""
    if not sys.platform.startswith("linux"):
        return
    import ctypes  # Linux only: prctl(PR_SET_PDEATHSIG)

    ctypes.CDLL(None, use_errno=True).prctl(1, signal.SIGTERM)  # 1: PR_SET_PDEATHSIG


# how often the launcher looks at its processes [s]
POLL_S = 0.2


def _wait(procs: list, a) -> int:
    """Wait for the local processes; when one fails, stop the others at once (they would wait
    at the next barrier for minutes and abort with a stack dump) and say how to resume."""
    while True:
        codes = [pr.poll() for pr in procs]
        bad = [i for i, c in enumerate(codes) if c not in (None, 0)]
        if bad or all(c == 0 for c in codes):
            break
        time.sleep(POLL_S)
    if not bad:
        return 0
    for pr in procs:
        if pr.poll() is None:
            pr.terminate()
    for pr in procs:
        try:
            pr.wait(timeout=10)
        except subprocess.TimeoutExpired:
            pr.kill()
            pr.wait()
    print(
        f"process {bad[0]} of {len(procs)} failed (exit code {codes[bad[0]]}); the others were stopped. Finished "
        f"blocks are kept in {a.out}: run the same command again to resume",
        file=sys.stderr,
    )
    return codes[bad[0]] if codes[bad[0]] > 0 else 1


def _run(p, a, pid: int, n_proc: int) -> int:

    t_start = time.perf_counter()
    common.enable_x64()

    if n_proc > 1:
        jax.config.update("jax_cpu_collectives_implementation", "gloo")
        jax.distributed.initialize(coordinator_address=a.coordinator, num_processes=n_proc, process_id=pid)
    options.use_compilation_cache(a)

    def barrier(name):
        if n_proc > 1:
            from jax.experimental import multihost_utils  # jax.distributed only: a one-process sweep never loads it

            multihost_utils.sync_global_devices(name)

    say = (lambda m: print(m, file=sys.stderr, flush=True)) if pid == 0 else (lambda m: None)
    try:  # the user's errors (the file, --out): an argparse-style exit
        plan = S.plan(problem_of(a))
        run.check_memory(plan, len(jax.local_devices()))  # this process's share (the launcher checked all)
        say(
            f"{a.spec}: {plan.n_runs} runs in {len(plan.blocks())} blocks of {plan.block} "
            f"({len(plan.groups)} group(s); {plan.n_steps} RK4 steps each), {n_proc} process(es) x "
            f"{len(jax.local_devices())} device(s)"
        )
        if pid == 0:
            resumed = run.prepare(plan, a.out, a.fresh)
            if resumed:
                say(f"resuming: {resumed} of {len(plan.blocks())} blocks already done in {a.out}")
    except ValueError as err:
        options.fail(p, str(err))
    barrier("sweep-prepared")
    if pid != 0 and run.read_state(a.out) is None:
        raise RuntimeError(
            f"{a.out}/{run.STATE_FILE} missing: process 0 did not prepare the output directory "
            "(with several hosts, --out must be one shared directory)"
        )
    t0 = time.perf_counter()
    stats = run.compute(plan, a.out, process_id=pid, num_processes=n_proc)
    stats["wall_s"] = time.perf_counter() - t0

    files.write_json(a.out / "blocks" / f"process_{pid}.json", stats)
    barrier("sweep-computed")
    if pid != 0:
        return 0
    say("writing runs.parquet")
    path = run.assemble(plan, a.out)
    table = report.read_table(path, columns=report.columns_needed(plan))
    say("certified radii and figures")
    certified = report.certified_radii(plan)
    summary = report.summarize(plan, table, certified)
    procs = [json.loads((a.out / "blocks" / f"process_{i}.json").read_text()) for i in range(n_proc)]
    summary = _header(a, plan) | summary
    summary["execution"] = _execution(plan, n_proc, len(jax.local_devices()), procs)
    summary["figures"] = report.figures(plan, table, certified, a.out)
    summary["wall_time_s"] = time.perf_counter() - t_start
    files.write_json(a.out / "summary.json", summary)
    c = summary["counts"]
    print(
        f"{plan.n_runs} runs: {c['converged']} converged, {c['not_converged']} not converged, {c['singular']} "
        f"singular, {c['failed']} failed; wrote {a.out}/runs.parquet, summary.json and "
        f"{len(summary['figures'])} figures ({summary['wall_time_s']:.0f} s)"
    )
    return 0


def _header(a, plan) -> dict:
    """The sweep's identifying fields, which lead summary.json."""
    return {
        "sweep": str(a.spec),
        "title": plan.spec.get("title", a.spec.stem),
        "law": str(plan.law),
        "task": str(plan.task),
        "initial_space": str(plan.space),
        "swept": plan.swept,
        "fingerprint": plan.fingerprint,
        "t_final": plan.t_final,
        "dt": plan.dt,
        "n_steps": plan.n_steps,
        "cases": [c for c, _ in plan.problem.cases() if c is not None],
        "problem": plan.problem.resolved(),
    }


def _execution(plan, n_proc: int, n_devices: int, procs: list) -> dict:
    """The execution block of summary.json, from the per-process block stats."""
    computed = sum(s["runs_computed"] for s in procs)
    compute_wall = max(s["wall_s"] for s in procs)
    return {
        "processes": n_proc,
        "devices_per_process": n_devices,
        "block": plan.block,
        "blocks": len(plan.blocks()),
        "runs_computed": computed,
        "runs_resumed": plan.n_runs - computed,
        "compute_wall_s": compute_wall,
        "first_calls_s": max(s["first_calls_s"] for s in procs),
        "throughput_runs_per_s": computed / compute_wall if compute_wall > 0 and computed else None,
        "throughput_trajectory_steps_per_s": computed * plan.n_steps / compute_wall
        if compute_wall > 0 and computed
        else None,
    }
