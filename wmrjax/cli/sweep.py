"""The sweep's command line: one process, ``--processes N`` local processes, or one process of
a multi-host run (``--coordinator HOST:PORT --process-id I --num-processes N``)."""

from __future__ import annotations

import os
import sys
import time
from pathlib import Path

import jax

from wmrjax.cli import launch, machine, options, problem_args, running
from wmrjax.problem import CASE_NAME, ProblemError
from wmrjax.sweep import job, run
from wmrjax.sweep import spec as S

DOC = """Run a sweep file: a controller over robots, references, initial conditions, gains and
actuator limits. Writes DIR/runs.parquet (one row per run), DIR/summary.json and PNG maps.
A killed sweep resumes from its finished blocks when rerun with the same file and --out."""


def parser():
    """The argument parser of ``wmrjax sweep``."""
    p = options.parser(DOC, default_out=None)
    problem_args.add_problem_options(p, needs="to sweep (see docs/problem_files.md)")
    p.add_argument("--out", type=Path, default=None, help="output directory (default: results/sweeps/<spec name>)")
    p.add_argument("--fresh", action="store_true", help=options.FRESH_HELP)
    p.add_argument(
        "--compare-gains",
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
    """Run ``wmrjax sweep`` with ``argv`` (default: the process's arguments); return the exit status."""
    p = parser()
    a = p.parse_args(argv)
    a.argv = list(sys.argv[1:] if argv is None else argv)  # a launcher's workers get the same problem
    distributed = a.coordinator is not None
    if distributed and (a.process_id is None or a.num_processes is None):
        options.fail(p, "--coordinator needs --process-id and --num-processes")
    if not distributed and (a.process_id is not None or a.num_processes is not None):
        options.fail(p, "--process-id and --num-processes need --coordinator HOST:PORT")
    if distributed and a.process_id >= a.num_processes:
        options.fail(p, f"--process-id {a.process_id} must be < --num-processes {a.num_processes}")
    if distributed and a.processes != 1:
        options.fail(p, "--processes starts local processes itself; do not combine it with --coordinator")
    if not a.file.is_file():
        options.fail(p, f"sweep file {str(a.file)!r} not found")
    if a.out is None:
        a.out = Path("results") / "sweeps" / a.file.stem
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
    machine.configure_xla(devices)  # before JAX starts its backend
    # one writer per --out: the launching process (its workers inherit the lock's token), or
    # process 0 of a run over several hosts
    running.prepare_output(p, a.out, lock=not distributed or a.process_id == 0, fresh=a.fresh)
    try:
        with running.reliable_interrupt():
            if a.processes > 1:
                _prepare(p, a, devices)
                return launch.launch(a, devices)
            return _run(p, a, a.process_id or 0, a.num_processes or 1)
    except ValueError as err:  # raised by the work (the file and --out were checked before it): exit 1
        running.fail_work(p, str(err), verbose=a.verbose)
    except KeyboardInterrupt:  # Ctrl-C: the finished blocks are kept, one line instead of a traceback
        running.interrupted(p, a.out)


def problem_of(a):
    """The sweep file's problem, paired with ``--compare-gains`` files as cases (``default`` and one per file)."""
    problem = problem_args.problem_from_args(a)
    if not a.compare_gains:
        return problem
    if "case" in problem.data:
        raise ProblemError(
            "--compare-gains pairs the file's own gains with tuned ones as [[case]]s; this file has [[case]]s "
            "already: add the tuned gains there"
        )
    files = a.compare_gains
    names = ["tuned"] if len(files) == 1 else [f.resolve().parent.name for f in files]
    if len(set(names)) != len(names) or not all(CASE_NAME.fullmatch(n) for n in names):
        names = [f"tuned_{i + 1}" for i in range(len(files))]
    cases = [{"name": "default"}] + [{"name": n, "gains": {"file": str(f.resolve())}} for n, f in zip(names, files)]
    return problem.with_values({"case": cases})


def _prepare(p, a, devices: int) -> None:
    """Before starting processes: refuse a bad file or another sweep's --out, check the memory."""
    machine.enable_x64()
    try:
        plan = S.plan(problem_of(a))
        run.check_memory(plan, devices, a.processes)
        run.prepare(plan, a.out, a.fresh)
    except ValueError as err:
        options.fail(p, str(err))


def _run(p, a, pid: int, n_proc: int) -> int:
    """One process of the sweep (of ``n_proc``): joins the others, computes its share; process 0
    writes the report and prints its counts."""
    t_start = time.perf_counter()
    machine.enable_x64()

    if n_proc > 1:
        jax.config.update("jax_cpu_collectives_implementation", "gloo")
        jax.distributed.initialize(coordinator_address=a.coordinator, num_processes=n_proc, process_id=pid)
    machine.use_compilation_cache(a)

    def barrier(name):
        if n_proc > 1:
            from jax.experimental import multihost_utils  # jax.distributed only: a one-process sweep never loads it

            multihost_utils.sync_global_devices(name)

    say = (lambda m: print(f"{a.file}: {m}", file=sys.stderr, flush=True)) if pid == 0 else (lambda m: None)
    try:  # the user's errors (the file, --out): an argparse-style exit
        plan = job.start(problem_of(a), a.out, fresh=a.fresh, process_id=pid, progress=say)
    except ValueError as err:
        options.fail(p, str(err))
    r = job.compute_share(
        plan,
        a.out,
        source=str(a.file),
        t_start=t_start,
        process_id=pid,
        num_processes=n_proc,
        barrier=barrier,
        progress=say,
    )
    if r is None:
        return 0
    c = r.counts
    print(
        f"{plan.n_runs} runs: {c['converged']} converged, {c['not_converged']} not converged, {c['singular']} "
        f"singular, {c['failed']} failed; wrote {a.out}/runs.parquet, summary.json and "
        f"{len(r.figures)} figures ({r.wall_time_s:.0f} s)"
    )
    return 0
