"""Running a planned sweep: one compiled program per group, blocks of runs spread over the
local devices (one block per device at a time, dispatched asynchronously so they run
together), every finished block written atomically (so a killed sweep resumes where it
stopped), several processes joined by ``jax.distributed``, and the table streamed into
Parquet by process 0.

A block is ``Plan.block`` runs and every device runs the same single-device program on it,
so every number in the table is the same whatever the number of devices or processes
(tested bit for bit; a program sharded over D devices is partitioned differently and
differs in the last bits).
"""

from __future__ import annotations

import json
import sys
import time
import zipfile
from pathlib import Path

import jax
import jax.numpy as jnp
import numpy as np

from wmrjax import _files as files
from wmrjax import _math, resources
from wmrjax.problem import Task, law_state
from wmrjax.sweep import spec as S

RESULT_COLUMNS = (
    "failed",
    "singular",
    "nonfinite",
    "inaccurate",
    "t_failure",
    "min_margin",
    "error_estimate",
    "final_position_error",
    "final_heading_error",
    "min_distance",
)
STATE_FILE = "sweep_state.json"


# --- the rollout of one run ------------------------------------------------------------------


def rollout_fn(plan: S.Plan, group: S.Group):
    """``one(varying) -> results`` for one run of ``group`` (pure; batched by the caller), with
    ``varying`` the run's inputs that differ across the group (:func:`payload`)."""
    ctrl = group.ctrl
    system = group.system()
    dynamic = plan.law == S.Law.DYNAMIC
    point = plan.task == S.Task.POINT and not dynamic
    treedef, constant, values = split(group)

    def one(varying):
        it = iter(varying)
        p, run = jax.tree_util.tree_unflatten(
            treedef, [jnp.asarray(v) if c else next(it) for c, v in zip(constant, values)]
        )
        key = None if run is None else jax.random.fold_in(jax.random.PRNGKey(group.noise_seed), run.astype(int))
        tr, params = group.run(p, save_every=plan.save_every, error_tol=plan.error_tol, noise_key=key)
        ref, g = params.reference, params.geometry
        zf = law_state(system, tr.final_state)
        tf = tr.t[-1]
        post_f = ref.posture(tf)
        pos = (ctrl.law.outputs(zf, g)[:2] - ref.position(tf)) if point else zf[:2] - post_f[:2]
        head = jnp.abs(_math.wrap_angle(zf[2] - post_f[2]))
        dg = tr.diagnostics
        out = dict(
            failed=dg.failed,
            singular=dg.singular,
            nonfinite=dg.nonfinite,
            inaccurate=dg.inaccurate,
            t_failure=dg.t_failure,
            min_margin=dg.min_margin,
            error_estimate=dg.error_estimate,
            final_position_error=jnp.linalg.norm(pos),
            final_heading_error=head,
        )
        if dynamic:
            states = law_state(system, tr.state)
            dist = jax.vmap(lambda z: ctrl.singular_distance(ctrl.psi(z, params), params))(states)
            out["min_distance"] = jnp.min(jnp.where(tr.valid, dist, jnp.inf))
        else:
            out["min_distance"] = jnp.full((), jnp.nan, tf.dtype)
        return out

    return one


def _noisy(group: S.Group) -> bool:
    return group.control_period is not None and any(group.noise_std)


def _sources(group: S.Group) -> tuple:
    """``(inputs, run)``: every rollout input at the level of its axis
    (:meth:`wmrjax.problem.Setting.inputs`), and the run's index in its group where it draws
    measurement noise (else None)."""
    return group.inputs(), (np.arange(group.size, dtype=float) if _noisy(group) else None)


def split(group: S.Group):
    """``(treedef, constant, values)``: the rollout inputs' structure, which leaves are the same
    for every run of the group, and their values. Constant leaves are compiled in (XLA folds
    them: the §6.1 loop runs twice as fast with its fixed geometry, gains and reference folded
    than with them as per-run arrays); the others are batched."""
    inputs, run = _sources(group)
    leaves, treedef = jax.tree_util.tree_flatten((inputs, run))
    same = lambda x: bool(np.all(np.asarray(x) == np.asarray(x)[:1]))
    # the initial conditions (and run indices) are always batched: they carry the batch axis
    flags = jax.tree_util.tree_map(same, inputs)._replace(initial=False)
    constant = jax.tree_util.tree_leaves((flags, None if run is None else False))
    return treedef, constant, [np.asarray(x)[0] for x in leaves]


def payload(group: S.Group, start: int, n: int, pad_to: int, constant: list) -> list:
    """The varying rollout inputs (leaves, in :func:`split`'s order; ``constant`` is its mask) of
    runs ``start .. start + n - 1`` of ``group``, padded (with copies of the last run) to ``pad_to``."""
    runs = np.arange(start, start + n)
    if pad_to > n:
        runs = np.concatenate([runs, np.full(pad_to - n, runs[-1])])
    idx = list(np.unravel_index(runs, group.shape))
    per_run = (group.inputs(idx), runs.astype(float) if _noisy(group) else None)
    return [x for x, c in zip(jax.tree_util.tree_leaves(per_run), constant) if not c]


# --- execution ---------------------------------------------------------------------------------


class Progress:
    """Chunks done, runs/s and ETA: a rewritten line on a terminal, plain lines every
    ``every`` seconds otherwise (a log)."""

    def __init__(
        self,
        total_runs: int,
        total_blocks: int,
        done_runs: int,
        done_blocks: int,
        every: float = 10.0,
        stream=None,
        prefix: str = "",
    ):
        self.total_runs, self.total_blocks = total_runs, total_blocks
        self.done_runs, self.done_blocks = done_runs, done_blocks
        self.start_runs = done_runs
        self.t0 = self.last = time.perf_counter()
        self.every = every
        self.stream = stream or sys.stderr
        self.tty = hasattr(self.stream, "isatty") and self.stream.isatty()
        self.prefix = prefix

    def update(self, runs: int, blocks: int) -> None:
        """Count ``runs`` and ``blocks`` done and print the progress line when due."""
        self.done_runs += runs
        self.done_blocks += blocks
        now = time.perf_counter()
        if self.tty or now - self.last >= self.every or self.done_blocks == self.total_blocks:
            self.last = now
            rate = (self.done_runs - self.start_runs) / max(now - self.t0, 1e-9)
            left = self.total_runs - self.done_runs
            eta = left / rate if rate > 0 else float("inf")
            line = (
                f"{self.prefix}blocks {self.done_blocks}/{self.total_blocks}, runs {self.done_runs}/{self.total_runs}, "
                f"{rate:,.0f} runs/s, ETA {eta:.0f} s"
            )
            if self.tty:
                end = "\n" if self.done_blocks == self.total_blocks else ""
                print("\r" + line + " " * 8, end=end, file=self.stream, flush=True)
            else:
                print(line, file=self.stream, flush=True)


def estimate(plan: S.Plan, devices: int, processes: int = 1):
    """The sweep's memory on this machine (:mod:`wmrjax.resources`): every device of every local
    process runs a block at a time, holding each run's samples (every ``distance_every`` steps;
    host devices share the machine's memory), beside each process's reference checks."""
    n_state = max(int(g.system().n_state or g.ctrl.n_state) for g in plan.groups)
    samples = plan.n_steps // plan.save_every + 1
    per_block = resources.samples_bytes(samples, n_state, 8, plan.block)
    check = max(resources.check_bytes(plan.t_final, g.ctrl.reference_jet_floats()) for g in plan.groups)
    return resources.Estimate(per_block * devices * processes, check * processes, processes)


def check_memory(plan: S.Plan, devices: int, processes: int = 1) -> None:
    """ValueError before anything compiles when the sweep would not fit in memory."""
    resources.check_fits(
        estimate(plan, devices, processes),
        f"{processes} process(es) x {devices} device(s), each running a block of {plan.block} runs "
        f"with {plan.n_steps // plan.save_every + 1} samples each",
        "lower [simulation] block, raise distance_every, or use fewer --processes/--devices",
    )


def block_path(out: Path, b: int) -> Path:
    """The file of block ``b`` under ``out``."""
    return out / "blocks" / f"block_{b:06d}.npz"


# every block file carries the sweep's fingerprint and its own place in the plan, so that a
# block of another sweep (copied, or left by a concurrent writer) is never assembled as this one's
BLOCK_KEYS = ("fingerprint", "block", "start", "n")


def block_problem(plan: S.Plan, out: Path, b: int) -> str | None:
    """Why block ``b``'s file cannot be used (None: it can, or it does not exist yet): torn
    (not a readable ``.npz``), of another sweep, of another place in the plan, or lacking a
    result column."""
    path = block_path(out, b)
    if not path.exists():
        return None
    _, start, n = plan.blocks()[b]
    try:
        with np.load(path, allow_pickle=False) as f:
            keys = set(f.files)
            if not set(BLOCK_KEYS) <= keys:
                return f"{path} carries no sweep fingerprint (a block of an older version or another program)"
            if str(f["fingerprint"]) != plan.fingerprint:
                return f"{path} belongs to another sweep (fingerprint {f['fingerprint']}, this one {plan.fingerprint})"
            if (int(f["block"]), int(f["start"]), int(f["n"])) != (b, start, n):
                return (
                    f"{path} holds block {int(f['block'])} (runs {int(f['start'])}+{int(f['n'])}), "
                    f"expected block {b} (runs {start}+{n})"
                )
            bad = [c for c in RESULT_COLUMNS if c not in keys or f[c].shape != (n,)]
            if bad:
                return f"{path} lacks result columns or has wrong lengths: {bad}"
    except (OSError, ValueError, EOFError, zipfile.BadZipFile) as exc:
        return f"{path} is torn or not an .npz file ({type(exc).__name__}: {exc})"
    return None


def block_done(plan: S.Plan, out: Path, b: int, log=None) -> bool:
    """Whether block ``b`` is on disk and usable; an unusable file is named (``log``), removed
    and so recomputed."""
    _check_is_a_file(block_path(out, b))
    why = block_problem(plan, out, b)
    if why is not None:
        (log or (lambda m: print(m, file=sys.stderr, flush=True)))(f"recomputing: {why}")
        block_path(out, b).unlink()
        return False
    return block_path(out, b).exists()


def _check_is_a_file(path: Path) -> None:
    """ValueError if something that is not a regular file (a directory, a pipe) stands where the
    sweep writes one of its files: it is not the sweep's to remove."""
    if path.exists() and not path.is_file():
        raise ValueError(f"{path} is not a regular file (a directory?): the sweep writes its file there; remove it")


def read_state(out: Path):
    """The sweep's state file under ``out`` (None if absent)."""
    p = out / STATE_FILE
    if not p.exists():
        return None
    _check_is_a_file(p)
    try:
        return json.loads(p.read_text())
    except ValueError as err:
        raise ValueError(f"{p} is not valid JSON ({err}); delete it or pass --fresh") from None


def prepare(plan: S.Plan, out: Path, fresh: bool) -> int:
    """Write (or check) the sweep's state file; returns the number of blocks already done.

    Raises:
      ValueError: the directory holds blocks of another sweep (and ``fresh`` is False).
    """
    _check_is_a_file(out / STATE_FILE)  # not even --fresh replaces a directory
    state = None if fresh else read_state(out)  # --fresh discards even a corrupt state file
    blocks = plan.blocks()
    want = {"fingerprint": plan.fingerprint, "n_runs": plan.n_runs, "n_blocks": len(blocks), "block": plan.block}
    if fresh or state is None or state.get("fingerprint") != plan.fingerprint:
        if state is not None and state.get("fingerprint") != plan.fingerprint and not fresh:
            done = list((out / "blocks").glob("block_*.npz")) if (out / "blocks").exists() else []
            if done:
                raise ValueError(
                    f"{out} holds {len(done)} finished blocks of another sweep (fingerprint "
                    f"{state.get('fingerprint')}, this one {plan.fingerprint}); use another --out or --fresh"
                )
        for f in (out / "blocks").glob("block_*.npz") if (out / "blocks").exists() else []:
            f.unlink()
        files.write_json(out / STATE_FILE, want)
        return 0
    return sum(block_path(out, b).exists() for b in range(len(blocks)))


def compute(plan: S.Plan, out: Path, *, process_id: int = 0, num_processes: int = 1) -> dict:
    """Compute this process's share of the blocks that are not on disk yet (block ``b`` belongs
    to process ``b % num_processes``); returns timing figures."""
    devices = jax.local_devices()
    D = len(devices)
    blocks = plan.blocks()
    mine = [b for b in range(len(blocks)) if b % num_processes == process_id]
    todo = [b for b in mine if not block_done(plan, out, b)]
    done_runs = sum(blocks[b][2] for b in set(mine) - set(todo))
    prog = Progress(
        sum(blocks[b][2] for b in mine),
        len(mine),
        done_runs,
        len(mine) - len(todo),
        prefix=f"[process {process_id}] " if num_processes > 1 else "",
    )
    t_first, t_run, n_run = 0.0, 0.0, 0
    by_group = {}
    for b in todo:
        by_group.setdefault(blocks[b][0], []).append(b)
    for gi, bs in by_group.items():
        group = plan.groups[gi]
        # one single-device program per group, the same on every device of every process: the
        # table does not depend on how blocks are spread (a sharded program over D devices is
        # partitioned differently and differs in the last bits)
        fn = jax.jit(jax.vmap(rollout_fn(plan, group)))
        _, constant, _ = split(group)
        for k in range(0, len(bs), D):
            ids = bs[k : k + D]
            t = time.perf_counter()
            pending = [
                fn(jax.device_put(payload(group, blocks[b][1], blocks[b][2], plan.block, constant), devices[j]))
                for j, b in enumerate(ids)
            ]  # dispatched asynchronously: the devices run together
            for b, res in zip(ids, pending):
                _, start, n = blocks[b]
                res = jax.tree_util.tree_map(lambda x: np.asarray(x)[:n], res)
                files.write_npz(
                    block_path(out, b),
                    fingerprint=np.str_(plan.fingerprint),
                    block=b,
                    start=start,
                    n=n,
                    **{c: res[c] for c in RESULT_COLUMNS},
                )
                n_run += n
            dt_ = time.perf_counter() - t
            if k == 0:  # the group's first call compiles
                t_first += dt_
            else:
                t_run += dt_
            prog.update(sum(blocks[b][2] for b in ids), len(ids))
    return {"blocks_computed": len(todo), "runs_computed": n_run, "first_calls_s": t_first, "later_calls_s": t_run}


def assemble(plan: S.Plan, out: Path):
    """Stream every block into ``runs.parquet`` (one row group per block) with its swept values;
    returns the path. Memory: one block at a time."""
    import pyarrow as pa  # optional dependency (the cli extra): only the Parquet table needs it

    blocks = plan.blocks()
    missing = [b for b in range(len(blocks)) if not block_path(out, b).exists()]
    if missing:
        raise RuntimeError(f"{len(missing)} blocks are missing (first: {missing[0]}); rerun the sweep to finish them")
    bad = [why for why in (block_problem(plan, out, b) for b in range(len(blocks))) if why is not None]
    if bad:  # changed since compute() checked them: refuse rather than mix another sweep's rows in
        raise ValueError(
            f"{len(bad)} block files cannot be used (first: {bad[0]}); rerun the same sweep command: it recomputes them"
        )
    names = value_columns(plan)
    # label columns (a gains file's name): null where a group has none, numbers NaN
    labels = {k for g in plan.groups for a in g.axes for k, v in a.columns.items() if np.asarray(v).dtype.kind in "US"}

    def batches():
        for b, (gi, start, n) in enumerate(blocks):
            group = plan.groups[gi]
            idx = S.unravel(group, start, n)
            cols = S.columns_of(group, idx)
            with np.load(block_path(out, b), allow_pickle=False) as f:
                res = {c: f[c] for c in RESULT_COLUMNS}
            data = {
                "run": np.arange(start, start + n) + sum(g.size for g in plan.groups[:gi]),
                **({"case": np.full(n, group.case)} if group.case is not None else {}),
                "robot": np.full(n, group.ctrl.robot.name),
                "level": np.full(n, str(group.ctrl.level)),
            }
            for k in names:
                data[k] = (
                    cols[k]
                    if k in cols
                    else np.full(n, None if k in labels else np.nan, dtype=object if k in labels else float)
                )
            data |= res
            data |= classify(plan, res)
            yield data

    def to_batch(d):
        return pa.record_batch({k: pa.array(v, type=pa.string() if k in labels else None) for k, v in d.items()})

    return files.write_parquet(out / "runs.parquet", (to_batch(d) for d in batches()))


def value_columns(plan: S.Plan) -> list:
    """The columns of the runs' values (swept or fixed), over every group, in axis order."""
    return list(dict.fromkeys(k for g in plan.groups for a in g.axes for k in a.columns))


OUTCOMES = ("converged", "not_converged", "singular", "failed")


def classify(plan: S.Plan, res: dict) -> dict:
    """``converged`` (regular, final errors within the tolerances), ``singular`` (flagged
    singular), ``failed`` (non-finite or inaccurate), else ``not_converged``."""
    pos_ok = res["final_position_error"] <= plan.position_tol
    head_ok = res["final_heading_error"] <= plan.heading_tol
    conv = ~res["failed"] & pos_ok & (head_ok if plan.task == Task.POSTURE else True)
    outcome = np.where(
        res["singular"], "singular", np.where(res["failed"], "failed", np.where(conv, "converged", "not_converged"))
    )
    return {"converged": conv, "outcome": outcome}
