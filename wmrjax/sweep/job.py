"""The sweep job (``wmrjax sweep``) as a library: plan a problem's runs, compute this process's
share of the blocks not yet on disk, and (process 0) assemble the table, the figures and
``summary.json`` into a :class:`wmrjax.sweep.report.SweepReport`.

One process: :func:`sweep`. Several (``jax.distributed`` initialized by the caller): every
process calls :func:`start` then :func:`compute_share` with the same arguments and a barrier
that waits for all of them; process 0 gets the report, the others ``None``."""

from __future__ import annotations

import json
import time
from pathlib import Path

import jax

from wmrjax import _files as files
from wmrjax.problem import Problem
from wmrjax.sweep import report, run
from wmrjax.sweep import spec as S


def _no_barrier(name: str) -> None:
    """One process: nothing to wait for."""


def sweep(problem: Problem, out: Path, *, source: str = "", fresh: bool = False, progress=None) -> report.SweepReport:
    """Run every case of ``problem`` over its swept inputs in one process, resuming the blocks
    already in ``out``; writes ``runs.parquet``, the figures and ``summary.json``.

    Args:
        problem: the problem (:class:`wmrjax.problem.Problem`) with its swept ranges.
        out: the output directory (``Path``; made if missing); a killed sweep resumes from it.
        source: the problem file as the user named it (``summary.json``'s ``sweep``; default:
            the problem's source).
        fresh: discard the blocks of an earlier sweep in ``out`` and start over.
        progress: called with each progress message (default: printed).

    Returns:
        the :class:`wmrjax.sweep.report.SweepReport`.
    """
    t_start = time.perf_counter()
    plan = start(problem, out, fresh=fresh, progress=progress)
    return compute_share(plan, out, source=source or str(problem.source or ""), t_start=t_start, progress=progress)


def start(problem: Problem, out: Path, *, fresh: bool = False, process_id: int = 0, progress=None) -> S.Plan:
    """Plan the sweep, check that this process's share fits its devices' memory, and (process 0)
    prepare ``out`` (refusing another sweep's blocks unless ``fresh``). ``ValueError`` for a bad
    problem or output directory, before anything compiles.

    Args:
        problem: the problem (:class:`wmrjax.problem.Problem`).
        out: the output directory (``Path``).
        fresh: discard an earlier sweep's blocks in ``out``.
        process_id: this process's index (0 prepares ``out``).
        progress: called with each progress message (default: printed).

    Returns:
        the sweep's :class:`wmrjax.sweep.spec.Plan`.
    """
    say = progress or (lambda msg: print(msg, flush=True))
    jax.config.update("jax_enable_x64", True)  # the job runs in float64
    plan = S.plan(problem)
    run.check_memory(plan, len(jax.local_devices()))
    say(
        f"{plan.n_runs} runs in {len(plan.blocks())} blocks of {plan.block} ({len(plan.groups)} group(s); "
        f"{plan.n_steps} RK4 steps each), {jax.process_count()} process(es) x {len(jax.local_devices())} device(s)"
    )
    if process_id == 0:
        resumed = run.prepare(plan, out, fresh)
        if resumed:
            say(f"resuming: {resumed} of {len(plan.blocks())} blocks already done in {out}")
    return plan


def compute_share(
    plan: S.Plan,
    out: Path,
    *,
    source: str,
    t_start: float,
    process_id: int = 0,
    num_processes: int = 1,
    barrier=_no_barrier,
    progress=None,
) -> report.SweepReport | None:
    """Compute this process's blocks (block ``b`` belongs to process ``b % num_processes``), then
    on process 0 assemble the report from every process's statistics.

    Args:
        plan: the plan :func:`start` returned.
        out: the output directory :func:`start` prepared.
        source: the problem file as the user named it.
        t_start: ``time.perf_counter()`` when the job started [s].
        process_id: this process's index.
        num_processes: the processes computing the sweep.
        barrier: ``barrier(name)`` returns when every process has reached it (one process: none).
        progress: called with each progress message (default: printed).

    Returns:
        process 0: the :class:`wmrjax.sweep.report.SweepReport`; the others: ``None``.
    """
    say = progress or (lambda msg: print(msg, flush=True))
    barrier("sweep-prepared")
    if process_id != 0 and run.read_state(out) is None:
        raise RuntimeError(
            f"{out}/{run.STATE_FILE} missing: process 0 did not prepare the output directory "
            "(with several hosts, --out must be one shared directory)"
        )
    t0 = time.perf_counter()
    stats = run.compute(plan, out, process_id=process_id, num_processes=num_processes)
    stats["wall_s"] = time.perf_counter() - t0
    files.write_json(out / "blocks" / f"process_{process_id}.json", stats)
    barrier("sweep-computed")
    if process_id != 0:
        return None
    say("writing runs.parquet, certified radii and figures")
    procs = [json.loads((out / "blocks" / f"process_{i}.json").read_text()) for i in range(num_processes)]
    return report.finish(plan, out, source, procs, len(jax.local_devices()), t_start)
