r"""Multi-seed study on equal terms: the gradient tuner against the baselines users would pick,
held-out loss against compute.

    wmrjax study --out results/tuning_study
    wmrjax study --problems section_6_1_plant wmrjax/examples/s_path.toml --seeds 10 --out DIR

Per problem (a shipped name or a problem file) and seed s, every method below searches the same
gains (:class:`wmrjax.tune.GainFamily`), is scored by the same training objective
(:func:`wmrjax.tune.loop.objective`, certificate term included) on the same scenarios, under the same
certified-region requirement when the problem has one (``[tune.requirement]`` or
``--require-radius``): the gradient keeps it (:mod:`wmrjax.tune.certified`), a baseline rejects a
candidate that misses it. Each comes in two variants, ``fixed`` (the seed's training set) and
``resampled`` (a fresh draw per gradient step or per batch of candidates; batch k of a baseline is
the draw of the gradient's step k, common random numbers):

* ``gradient`` -- :func:`wmrjax.tune.loop.tune` with the problem's optimizer, steps and early stopping;
* ``random_search``, ``cma_es``, ``optuna_tpe``, ``optuna_cmaes`` -- :mod:`wmrjax.tune.baselines`.

Compute is counted in *forward-rollout equivalents*: a baseline's candidate costs ``n_train``;
a gradient step over B scenarios costs B times the measured ratio of the wall time of one
gradient step over B scenarios to that of one forward evaluation of B scenarios (both after
compilation, the fastest of a few repeats, measured once per problem on seed 0's set; the
forward evaluation is a baseline's, one candidate of a batched chunk); the gradient's
validation runs (which pick its parameters) cost ``n_validation`` each. Every baseline gets the
gradient run's planned budget (all its steps and validations) times ``--budget``. Wall seconds
are measured after compilation for every method (the gradient's from its first step, which
compiles only the optimizer update's small program; its resampled variant's include the loop's
bookkeeping evaluation of the fixed set each step).

At ``--points`` log-spaced compute points up to the budget the study records the held-out loss
of each method's best-so-far parameters: a baseline's best training objective among the
candidates it paid for; the gradient's best *validation* objective among the iterates it
validated (the parameters :func:`wmrjax.tune.loop.tune` would return if stopped there). Before any
candidate is paid for, a method holds the problem's initial gains. A gradient run that stopped
early holds its parameters at the later points.

Writes, resumably (one ``NAME/seed_S.json`` per problem and seed, atomically; a finished one
whose configuration fingerprint matches is kept; ``NAME/cost.json``: the measured ratio, kept
the same way):

* ``study.csv`` -- one row per problem x method x seed x compute point: compute [forward-rollout
  equivalents], seconds spent, held-out loss;
* ``summary.json`` -- per problem and method, the median and interquartile range over seeds of
  the final held-out loss and of the seconds, and the compute (forward equivalents, seconds) at
  which the method's median curve first comes within 1 % of each other method's final median
  held-out loss (None: never), and the tables in Markdown;
* ``study.png`` -- per problem: held-out loss against compute, median line and IQR band per
  method, log axes.
"""

from __future__ import annotations

import csv
import dataclasses
import functools
import hashlib
import io as _stdio
import json
import time
from pathlib import Path
from typing import NamedTuple

import jax
import numpy as np

from wmrjax import _files as files
from wmrjax.examples import PROBLEMS
from wmrjax.report import JobReport
from wmrjax.tune import baselines, config, loop
from wmrjax.tune.scenarios import draw_set

BASES = ("gradient", "random_search", "cma_es", "optuna_tpe", "optuna_cmaes")
METHODS = tuple(m + v for m in BASES for v in ("", "_resampled"))
REPO = Path(__file__).resolve().parents[1]
DEFAULT_PROBLEMS = ("section_6_1_plant", "car_schedule", "torque_2_1", "wmrjax/examples/s_path.toml")
TOLERANCE = 0.01  # "within 1 %" of another method's final median held-out loss
VERSION = 1  # bump when what a seed's file holds changes (its fingerprint then differs)
FIELDS = ("problem", "method", "seed", "point", "compute_fwd", "seconds", "heldout_loss")


def problem_path(family: str) -> tuple[str, Path]:
    """``(name, file)`` of a shipped problem name or a problem file (ValueError otherwise); a
    relative path that does not exist from here is looked up from the repository's root."""
    if family in PROBLEMS:
        return family, PROBLEMS[family]
    for path in (Path(family), REPO / family):
        if path.is_file():
            return path.stem, path
    raise ValueError(f"--problems: {family!r} is neither a shipped problem ({', '.join(sorted(PROBLEMS))}) nor a file")


# --- one problem ----------------------------------------------------------------------------------


class Plan(NamedTuple):
    """What every seed of one problem shares (built and compiled once)."""

    name: str
    problem: object  # wmrjax.problem.Problem
    setting: object
    settings: object  # wmrjax.tune.config.TuneSettings
    family: object
    raw0: np.ndarray
    evaluate: object  # wmrjax.tune.baselines.candidate_evaluator of the training objective
    requirement: object  # wmrjax.tune.certified.Requirement or None
    feasible: object  # raw -> bool, or None
    note: str  # why a requested requirement does not apply ('' otherwise)
    draw: object  # key -> a training batch (the resampled variants' draws), compiled


def plan(name: str, problem, require=None) -> Plan:
    """The :class:`Plan` of a problem; ``require`` (a radius, 'initial' or 'box', and a slice)
    replaces its requirement where the problem can keep one."""
    note, kept = "", None
    if require is not None:
        trial = problem.with_values({"tune.requirement": {"radius": require[0], "slice": require[1]}})
        s = trial.setting("tuning")
        try:
            ts = config.read(trial.section("tune"), trial.section("certify"))
            # checked (certified.check) and resolved: "initial" can prove nothing (a held reach at 3 noise_std)
            fam = ts.gain_family(s)
            kept = loop.keep(s, fam, ts.requirement, loop.initial_raw(s, fam))
            problem = trial
        except ValueError as err:  # e.g. a random reference family: no fixed path to certify
            note = f"requirement not applied: {err}"
    setting = problem.setting("tuning")
    settings = config.read(problem.section("tune"), problem.section("certify"))
    family = settings.gain_family(setting)
    loop.check(setting, family, settings.scenarios, settings.loss)
    raw0 = np.asarray(loop.initial_raw(setting, family))
    weights = jax.numpy.asarray(tuple(settings.loss), float)
    cert = loop.certificate(setting, settings.loss.certificate)

    def objective(raw, scen):  # the cli's training objective (certificate term included)
        val, ok, _ = loop.mean_loss(raw, scen, setting, family, weights)
        return loop.objective(val, ok) + loop.certificate_term(family, raw, cert)

    evaluate = baselines.candidate_evaluator(objective, family.shape, compiler_options=loop.LOOP_COMPILE)
    req = settings.requirement
    if req is not None and kept is None:  # the problem's own requirement
        kept = loop.keep(setting, family, req, raw0)
    feasible = baselines.requirement_check(kept) if req is not None else None
    n, mismatch = settings.scenarios.train, settings.scenarios.mismatch
    # one program for every seed's batches, compiled here: a baseline's seconds hold no compilation
    draw = jax.jit(lambda key: draw_set(setting, mismatch, jax.random.split(key, n)))
    jax.block_until_ready(draw(jax.random.PRNGKey(0)))
    return Plan(name, problem, setting, settings, family, raw0, evaluate, req, feasible, note, draw)


def measure_cost(p: Plan, repeats: int = 3) -> dict:
    """Wall seconds of one gradient step over the B training scenarios and of one forward
    evaluation of B scenarios (a 16-candidate chunk of the baselines' evaluator over 16), after
    compilation, the fastest of ``repeats`` (the least disturbed by other work on the machine);
    their ratio is a gradient rollout in forward rollouts."""
    ctx = loop.prepare(p.setting, p.family, p.settings.scenarios, p.settings.loss, 0)
    raw = jax.numpy.asarray(p.raw0)
    # the loop's own program (compiled at LOOP_COMPILE), so the ratio is what tune() pays
    step = lambda: jax.block_until_ready(loop._gradient_step(raw, ctx.sets.train, p.setting, p.family, ctx.weights))
    chunk = np.repeat(p.raw0[None], 16, axis=0)
    fwd = lambda: p.evaluate(chunk, scenarios=ctx.sets.train)
    times = {}
    for key, fn in (("gradient_step_s", step), ("forward_s", fwd)):
        fn()  # compiles
        times[key] = min(_timed(fn) for _ in range(repeats))
    times["forward_s"] /= 16
    times["ratio"] = times["gradient_step_s"] / times["forward_s"]
    times["n_train"] = p.settings.scenarios.train
    return times


def _timed(fn) -> float:
    t = time.perf_counter()
    fn()
    return time.perf_counter() - t


def validations(steps: int, eval_every: int) -> list[int]:
    """The steps (0-based) at which :func:`wmrjax.tune.loop.tune` validates (as its ``_record`` does)."""
    return [s for s in range(steps) if (s + 1) % eval_every == 0 or s == 0 or s + 1 == steps]


def gradient_budget(settings, ratio: float) -> float:
    """Forward-rollout equivalents of a full gradient run: its steps and its validations."""
    sc = settings.scenarios
    return (
        settings.steps * sc.train * ratio
        + len(validations(settings.steps, settings.stopping.eval_every)) * sc.validation
    )


def compute_points(budget: float, n: int) -> np.ndarray:
    """``n`` compute points, log-spaced by factors of 2 up to ``budget`` (one: the budget)."""
    return budget / 2.0 ** np.arange(n - 1, -1, -1)


# --- one seed -------------------------------------------------------------------------------------


class Trace(NamedTuple):
    """A run's spending and choices: after unit i (a step or a candidate) it had spent
    ``costs[i]`` forward-rollout equivalents and ``seconds[i]`` s; ``picks`` are (unit index,
    raw) where its chosen parameters changed."""

    costs: np.ndarray
    seconds: np.ndarray
    picks: list


def gradient_trace(p: Plan, seed: int, resample: bool, cost: dict) -> Trace:
    """Run :func:`wmrjax.tune.loop.tune` and return its :class:`Trace` (picks: each new best
    validation objective; the history's parameters mapped back to raw ones).

    Seconds are the time stamps of tune's per-step log lines, except the first step's: tune
    compiles its optimizer update (a new program per call), and on the first run the validation
    and bookkeeping programs, in its first step, so that step is charged the measured time of
    one gradient step and one validation instead (``cost``: :func:`measure_cost`)."""
    ratio = cost["ratio"]

    s = p.settings
    scen = s.scenarios._replace(resample=resample)
    stamps = []

    def log(msg):  # tune logs one line per step, after its update: the step's end
        if msg.startswith("step "):
            stamps.append(time.perf_counter())

    res = loop.tune(
        p.setting,
        p.family,
        s.optimizer.build(s.steps),
        steps=s.steps,
        scenarios=scen,
        loss=s.loss,
        stopping=s.stopping,
        seed=seed,
        log=log,
        requirement=p.requirement,
    )
    costs, spent, picks, best = [], 0.0, [], np.inf
    for i, h in enumerate(res.history):
        spent += scen.train * ratio + (scen.validation if "validation_loss" in h else 0)
        costs.append(spent)
        if "validation_loss" in h and h["validation_loss"] < best:
            best = h["validation_loss"]
            picks.append((i, np.asarray(p.family.raw_from_positive(np.asarray(h["params"])))))
    first = cost["gradient_step_s"] + scen.validation * cost["forward_s"]
    return Trace(np.asarray(costs), np.asarray(stamps) - stamps[0] + first, picks)


def baseline_trace(p: Plan, method: str, seed: int, resample: bool, sets, budget: int) -> Trace:
    """Run one baseline of :mod:`wmrjax.tune.baselines` on the seed's training set (or resampled
    batches: the draws of the gradient's steps) and return its :class:`Trace`."""
    s, b = p.settings, p.settings.baselines
    stream = jax.random.fold_in(jax.random.PRNGKey(seed), 3)  # tune()'s stream of resampled batches
    kw = dict(
        budget_rollouts=budget,
        n_train=s.scenarios.train,
        seed=1000 * seed,
        feasible=p.feasible,
        scenarios_for=(lambda k: p.draw(jax.random.fold_in(stream, k))) if resample else None,
    )
    box = dict(low=b.search_low, high=b.search_high)
    cma = dict(population=b.population(p.family.size), sigma=b.cma_sigma)
    extra = {"random_search": box, "optuna_tpe": box, "cma_es": cma, "optuna_cmaes": {**cma, **box}}[method]
    evaluate = functools.partial(p.evaluate, scenarios=sets.train)
    run = getattr(baselines, method)(p.family, evaluate, p.raw0, **kw, **extra)
    costs = np.arange(1, len(run.best_so_far) + 1) * run.rollouts_per_candidate
    return Trace(costs.astype(float), np.asarray(run.seconds), [(k, np.asarray(r)) for k, r in run.improvements])


def at_points(trace: Trace, points, raw0):
    """``(raws, seconds)`` at each compute point: the parameters chosen from the units paid for
    by then (``raw0`` before any) and the seconds spent on them."""
    raws, secs = [], []
    for c in points:
        n = int(np.searchsorted(trace.costs, c * (1 + 1e-12), side="right"))  # units within c (rounding)
        chosen = [r for k, r in trace.picks if k < n]
        raws.append(np.asarray(chosen[-1] if chosen else raw0))
        secs.append(float(trace.seconds[n - 1]) if n else 0.0)
    return raws, secs


def run_seed(p: Plan, seed: int, methods, points, cost: dict, budget: float, say=print) -> dict:
    """Every method on one seed: ``{"initial_heldout", "methods": {method: {compute_fwd,
    seconds, heldout_loss (lists over points), total_compute_fwd, total_seconds}}}``."""
    s = p.settings
    sets = loop.prepare(p.setting, p.family, s.scenarios, s.loss, seed).sets
    chosen = {}
    for m in methods:
        base, resample = m.removesuffix("_resampled"), m.endswith("_resampled")
        say(f"{p.name}, seed {seed}: {m}")
        tr = (
            gradient_trace(p, seed, resample, cost)
            if base == "gradient"
            else baseline_trace(p, base, seed, resample, sets, int(budget))
        )
        chosen[m] = (tr, *at_points(tr, points, p.raw0))
    # every chosen parameter set once on the held-out scenarios (they repeat across points)
    every = [p.raw0] + [r for _, raws, _ in chosen.values() for r in raws]
    keys = [r.tobytes() for r in every]
    uniq = dict(zip(keys, every))
    held = dict(zip(uniq, p.evaluate(np.stack(list(uniq.values())), scenarios=sets.heldout)))
    out = {"initial_heldout": float(held[keys[0]]), "methods": {}}
    for m, (tr, raws, secs) in chosen.items():
        out["methods"][m] = {
            "compute_fwd": [float(c) for c in points],
            "seconds": secs,
            "heldout_loss": [float(held[r.tobytes()]) for r in raws],
            "total_compute_fwd": float(tr.costs[-1]),
            "total_seconds": float(tr.seconds[-1]),
        }
    return out


# --- aggregation ------------------------------------------------------------------------------------


def rows_of(problem: str, seed: int, result: dict) -> list[dict]:
    """Table rows (:data:`FIELDS`) of one seed's result."""
    rows = []
    for m, r in result["methods"].items():
        for j, (c, sec, h) in enumerate(zip(r["compute_fwd"], r["seconds"], r["heldout_loss"])):
            rows.append(dict(problem=problem, method=m, seed=seed, point=j, compute_fwd=c, seconds=sec, heldout_loss=h))
    return rows


def _stats(v) -> dict:
    """Median and interquartile range (NumPy's linear percentiles) of ``v``."""
    q25, med, q75 = (float(x) for x in np.percentile(np.asarray(v, float), [25, 50, 75]))
    return {"median": med, "q25": q25, "q75": q75, "iqr": q75 - q25, "n": len(v)}


def curves(rows: list[dict]) -> dict:
    """``{problem: {method: {"compute_fwd", "median", "q25", "q75", "seconds"}}}``: per compute
    point the held-out loss's median and quartiles over seeds and the median seconds."""
    out = {}
    for r in rows:
        out.setdefault(r["problem"], {}).setdefault(r["method"], {}).setdefault(r["point"], []).append(r)
    for P in out.values():
        for m, pts in P.items():
            js = sorted(pts)
            st = [_stats([r["heldout_loss"] for r in pts[j]]) for j in js]
            P[m] = {
                "compute_fwd": [pts[j][0]["compute_fwd"] for j in js],
                "median": [s["median"] for s in st],
                "q25": [s["q25"] for s in st],
                "q75": [s["q75"] for s in st],
                "seconds": [float(np.median([r["seconds"] for r in pts[j]])) for j in js],
            }
    return out


def aggregate(rows: list[dict], tolerance: float = TOLERANCE) -> dict:
    """Per problem and method: the final held-out loss (last compute point) and the seconds
    there, median and IQR over seeds; and for each other method B, the compute at which this
    method's median curve first reaches (1 + tolerance) x B's final median held-out loss
    (``compute_fwd`` and the median ``seconds`` at that point; None when never)."""
    cur, out = curves(rows), {}
    for problem, P in cur.items():
        out[problem] = {}
        for m, c in P.items():
            last = len(c["compute_fwd"]) - 1
            fin = [r for r in rows if r["problem"] == problem and r["method"] == m and r["point"] == last]
            out[problem][m] = {
                "final_heldout_loss": _stats([r["heldout_loss"] for r in fin]),
                "final_seconds": _stats([r["seconds"] for r in fin]),
                "budget_fwd": c["compute_fwd"][-1],
                "to_within": {},
            }
        for m, c in P.items():
            for other in P:
                if other == m:
                    continue
                target = (1 + tolerance) * out[problem][other]["final_heldout_loss"]["median"]
                j = next((j for j, v in enumerate(c["median"]) if v <= target), None)
                out[problem][m]["to_within"][other] = {
                    "target": target,
                    "compute_fwd": None if j is None else c["compute_fwd"][j],
                    "seconds": None if j is None else c["seconds"][j],
                }
    return out


def ordered(methods) -> list:
    """The methods in :data:`METHODS` order, any others after them (sorted)."""
    return [m for m in METHODS if m in methods] + sorted(m for m in methods if m not in METHODS)


def markdown(agg: dict, tolerance: float = TOLERANCE) -> str:
    """Per problem, two Markdown tables: final held-out loss and seconds (median [q25, q75]);
    and the compute (forward-rollout equivalents / seconds) each method (row) needs to come
    within ``tolerance`` of each other method's (column) final median held-out loss."""
    q = lambda s, f="{:.4g}": f"{f.format(s['median'])} [{f.format(s['q25'])}, {f.format(s['q75'])}]"
    lines = []
    for problem, P in agg.items():
        ms = ordered(P)
        lines += [
            f"### {problem}",
            "",
            "| method | final held-out loss, median [IQR] | seconds, median [IQR] | budget [fwd-rollout eq.] |",
            "|---|---|---|---|",
        ]
        lines += [
            f"| {m} | {q(P[m]['final_heldout_loss'])} | {q(P[m]['final_seconds'], '{:.3g}')} | "
            f"{P[m]['budget_fwd']:.0f} |"
            for m in ms
        ]
        lines += [
            "",
            f"compute to come within {100 * tolerance:g} % of the column's final median held-out loss "
            "(forward-rollout equivalents / s; '-': never within the budget)",
            "",
            "| method | " + " | ".join(ms) + " |",
            "|---" * (len(ms) + 1) + "|",
        ]
        for m in ms:
            cell = lambda o: (
                ""
                if o == m
                else "-"
                if P[m]["to_within"][o]["compute_fwd"] is None
                else f"{P[m]['to_within'][o]['compute_fwd']:.0f} / {P[m]['to_within'][o]['seconds']:.3g}"
            )
            lines.append(f"| {m} | " + " | ".join(cell(o) for o in ms) + " |")
        lines.append("")
    return "\n".join(lines)


# --- the study ------------------------------------------------------------------------------------


def _fingerprint(*parts) -> str:
    return hashlib.sha256(json.dumps(parts, sort_keys=True, default=str).encode()).hexdigest()[:16]


def _kept(path: Path, fp: str):
    """The JSON at ``path`` when it exists and carries fingerprint ``fp`` (None otherwise)."""
    if not path.exists():
        return None
    try:
        d = json.loads(path.read_text())
    except (OSError, json.JSONDecodeError):
        return None  # a torn or foreign file: computed again
    return d if isinstance(d, dict) and d.get("fingerprint") == fp else None


def problem_cost(p: Plan, out: Path, say=print) -> dict:
    """The measured cost ratio of a problem (``NAME/cost.json``: kept while the problem is the
    same, so every seed, and a resumed study, charges the same)."""
    fp = _fingerprint(VERSION, p.problem.fingerprint(), repr(p.family))
    cost = _kept(out / p.name / "cost.json", fp)
    if cost is None:
        say(f"{p.name}: compiling and timing a gradient step and a forward evaluation")
        cost = {"fingerprint": fp, **measure_cost(p)}
        files.write_json(out / p.name / "cost.json", cost)
    return cost


def study(
    problems: dict, out, *, seeds: int, methods=METHODS, points: int = 8, budget: float = 1.0, log=print
) -> StudyReport:
    """Run (or resume) the study of ``problems`` into ``out`` and write its three files.

    Args:
        problems: name -> ``(Problem, requirement)``, the requirement ``(radius, slice)`` or None.
        out: the output directory (``str`` or ``Path``; made if missing); finished seeds are kept.
        seeds: seeds per problem and method.
        methods: the methods compared (:data:`METHODS`).
        points: compute points per curve.
        budget: the baselines' budget as a multiple of the gradient's.
        log: called with each progress message.

    Returns:
        the :class:`StudyReport`.
    """
    out = Path(out)
    out.mkdir(parents=True, exist_ok=True)
    token = files.acquire_output(out, "wmrjax.tune.study")  # a second writer is refused (OutputLocked)
    try:
        t0, rows, notes, costs = time.perf_counter(), [], {}, {}
        methods = [m for m in METHODS if m in methods]
        total, done = len(problems) * seeds, 0
        for name, (problem, require) in problems.items():
            p = plan(name, problem, require)
            notes[name], costs[name] = p.note, problem_cost(p, out, log)
            b = gradient_budget(p.settings, costs[name]["ratio"])
            pts = compute_points(b, points)
            _check_budget(p, budget * b)
            for seed in range(seeds):
                fp = _fingerprint(
                    VERSION,
                    p.problem.fingerprint(),
                    repr(p.family),
                    seed,
                    methods,
                    pts.tolist(),
                    budget,
                    costs[name]["ratio"],
                    repr(p.requirement),
                )
                path = out / name / f"seed_{seed}.json"
                res = _kept(path, fp)
                elapsed = time.perf_counter() - t0
                if res is None:
                    log(f"{name}, seed {seed} ({done + 1}/{total}, {elapsed:.0f} s so far)")
                    res = {"fingerprint": fp, **run_seed(p, seed, methods, pts, costs[name], budget * b, log)}
                    files.write_json(path, res)
                else:
                    log(f"{name}, seed {seed}: done earlier, kept")
                done += 1
                rows += rows_of(name, seed, res)
        return _write(out, rows, notes, costs, seeds, budget, time.perf_counter() - t0, log)
    finally:
        files.release_output(out, token)


def _check_budget(p: Plan, budget: float) -> None:
    """ValueError when the baselines' budget is less than one CMA-ES generation."""
    b, n = p.settings.baselines, p.settings.scenarios.train
    pop = b.population(p.family.size)
    if budget < pop * n:
        raise ValueError(
            f"{p.name}: a budget of {budget:.0f} forward rollouts is less than one CMA-ES generation "
            f"({pop} x {n}); raise --budget or the steps"
        )


@dataclasses.dataclass(frozen=True)
class StudyReport(JobReport):
    """The study's result (:func:`study`): every method's loss against compute, per problem.

    Attributes:
        problems: the problems' names.
        seeds: the seeds per problem and method.
        budget: the baselines' budget as a multiple of the gradient's.
        costs: per problem, the measured cost of a gradient step in forward rollouts (``ratio``).
        notes: per problem, how its certified-radius requirement was set ("" without one).
        rows: one row per problem, seed, method and compute point (the columns of ``study.csv``,
            :data:`FIELDS`).
        aggregate: per problem and method, the median and interquartile range over seeds
            (:func:`aggregate`).
        wall_time_s: the job's wall time [s].
    """

    problems: tuple
    seeds: int
    budget: float
    costs: dict
    notes: dict
    rows: tuple
    aggregate: dict
    wall_time_s: float

    @property
    def table_markdown(self) -> str:
        """The aggregate as Markdown tables, one per problem (:func:`markdown`)."""
        return markdown(self.aggregate)

    def summary(self) -> dict:
        """``summary.json`` (plain JSON)."""
        return files.jsonable(
            {
                "experiment": "tuning study on equal terms",
                "problems": list(self.problems),
                "seeds": self.seeds,
                "statistic": "median and interquartile range (25th-75th percentile) over seeds",
                "compute_unit": "forward-rollout equivalents (one scenario simulated once, forward)",
                "cost_per_problem": self.costs,
                "baseline_budget_multiple": self.budget,
                "tolerance": TOLERANCE,
                "requirement_notes": {k: v for k, v in self.notes.items() if v},
                "aggregate": self.aggregate,
                "table_markdown": self.table_markdown,
                "wall_time_s": self.wall_time_s,
            }
        )


def _write(out: Path, rows, notes, costs, seeds, budget, wall, log) -> StudyReport:
    """``study.csv``, ``summary.json`` and ``study.png`` of the rows."""
    buf = _stdio.StringIO()
    wr = csv.DictWriter(buf, fieldnames=list(FIELDS))
    wr.writeheader()
    wr.writerows(rows)
    files.write_bytes(out / "study.csv", buf.getvalue().encode())
    figure(out / "study.png", rows)
    report = StudyReport(tuple(costs), seeds, budget, costs, notes, tuple(rows), aggregate(rows), wall)
    report.write_summary(out)
    log(report.table_markdown)
    return report


def figure(path: Path, rows: list[dict]) -> None:
    """Held-out loss against compute per problem: median line and IQR band per method (solid:
    fixed training set, dashed: resampled)."""
    plt = files.headless_pyplot()
    cur = curves(rows)
    fig, axs = plt.subplots(1, len(cur), figsize=(5.0 * len(cur), 4.2), squeeze=False)
    for ax, (problem, P) in zip(axs[0], cur.items()):
        bases = list(dict.fromkeys(m.removesuffix("_resampled") for m in ordered(P)))
        for m in ordered(P):
            c, color = P[m], f"C{bases.index(m.removesuffix('_resampled')) % 10}"
            ls = "--" if m.endswith("_resampled") else "-"
            ax.plot(
                c["compute_fwd"], c["median"], ls, color=color, lw=1.4, marker="o", ms=2.5, label=m.replace("_", " ")
            )
            ax.fill_between(c["compute_fwd"], c["q25"], c["q75"], color=color, alpha=0.12, lw=0)
        ax.set_xscale("log")
        ax.set_yscale("log")
        ax.set_xlabel("compute [forward-rollout equivalents]")
        ax.set_ylabel("held-out loss (training objective)")
        ax.set_title(problem)
        ax.grid(alpha=0.3, which="both")
        ax.legend(fontsize=6)
    fig.suptitle("held-out loss of the best-so-far gains vs compute (median, band: IQR over seeds)")
    fig.tight_layout()
    files.write_png(fig, path)
    plt.close(fig)
