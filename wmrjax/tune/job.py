"""The tuning job (``wmrjax tune``): the gradient run through the simulator
(:func:`wmrjax.tune.loop.tune`, resumable), its evaluation on held-out scenarios, the baselines
(random search and CMA-ES) at the same budget, the certified radii of the initial and tuned
gains, and ``gains.json``, ``history.json``, the figures and ``summary.json``."""

from __future__ import annotations

import dataclasses
import functools
import time
from concurrent.futures import ThreadPoolExecutor
from pathlib import Path

import jax
import jax.numpy as jnp
import numpy as np

from wmrjax import _files as files
from wmrjax import references as R
from wmrjax.problem import Problem, Setting, gains_file_dict, gains_owner, law_state
from wmrjax.report import JobReport
from wmrjax.tune import baselines, certified, config, loop
from wmrjax.tune.gains import GainFamily
from wmrjax.tune.scenarios import rollout


@dataclasses.dataclass(frozen=True)
class TuneReport(JobReport):
    """What :func:`run` found: the tuned gains, their losses beside the initial gains' and the
    baselines', and the certified radii of both.

    Attributes:
        problem: the problem tuned.
        setting: its closed loop (:meth:`wmrjax.problem.Problem.setting`).
        settings: the ``[tune]`` section (:class:`wmrjax.tune.config.TuneSettings`).
        family: the gain parameterization tuned (:class:`wmrjax.tune.GainFamily`).
        result: the gradient run (:class:`wmrjax.tune.TuneResult`: history, best parameters, rollouts).
        initial_raw: ``(family.size,)`` the initial gains' raw parameters.
        tuned_raw: ``(family.size,)`` the tuned gains' (the best validation loss of the run).
        train_loss: the training objective of ``(initial, tuned)`` gains.
        heldout_loss: the held-out objective of ``(initial, tuned)`` gains (+inf where not finite).
        heldout_ok: ``(2, n_heldout)`` which held-out scenarios ran without failing, per gains.
        heldout_metrics: the held-out loss terms per gains and scenario (leading axis 2).
        baselines: random search and CMA-ES at the same budget, per method: per seed, the best
            losses and the rollouts used.
        rollouts_to_match: per baseline, the gradient's rollouts to reach its best loss.
        radii: the certified radii of the initial and tuned gains, the requirement and how it was
            kept (:func:`wmrjax.tune.certified.radii`; ``{"skipped": reason}`` without a certificate).
        best_heldout: the method and seed with the lowest held-out loss, whose gains are in
            :data:`BEST_FILE`.
        gradient_wall_time_s: the gradient run's wall time, compilation included [s].
        wall_time_s: the job's wall time [s].
    """

    problem: Problem
    setting: Setting
    settings: config.TuneSettings
    family: GainFamily
    result: loop.TuneResult
    initial_raw: jax.Array
    tuned_raw: jax.Array
    train_loss: tuple
    heldout_loss: tuple
    heldout_ok: np.ndarray
    heldout_metrics: object
    baselines: dict
    rollouts_to_match: dict
    radii: dict
    best_heldout: dict
    gradient_wall_time_s: float
    wall_time_s: float

    @property
    def tuned_gains(self):
        """The tuned gains (:class:`wmrjax.Gains` or :class:`wmrjax.GainSchedule`), as ``gains.json``."""
        return self.family.gains(self.tuned_raw)

    @property
    def initial_gains(self):
        """The initial gains, in the same parameterization."""
        return self.family.gains(self.initial_raw)

    def summary(self) -> dict:
        """``summary.json`` (plain JSON); it is a gains file too (the tuned gains)."""
        return files.jsonable(_summary(self) | {"best_heldout": self.best_heldout, "wall_time_s": self.wall_time_s})


def run(problem, out: Path, fresh: bool = False, log=print, progress=None, falsify: bool = False) -> TuneReport:
    """Tune, evaluate, run the baselines, write ``gains.json``, the figures and ``summary.json``.

    Args:
        problem: the problem (:class:`wmrjax.problem.Problem`) with its ``[tune]`` section.
        out: the output directory (``Path``; made if missing), which holds the resumable checkpoint.
        fresh: start over, discarding a checkpoint in ``out``.
        log: called with each line of the run's log.
        progress: called with each stage's message (default: ``log``).
        falsify: also falsify the exact-map radii of the initial and tuned gains.

    Returns:
        the :class:`TuneReport`.
    """
    jax.config.update("jax_enable_x64", True)  # this entry point runs in float64

    say = progress or log
    setting = problem.setting("tuning")
    settings = config.read(problem.section("tune"), problem.section("certify"))
    family = settings.gain_family(setting)
    out.mkdir(parents=True, exist_ok=True)
    if fresh and (out / "checkpoint.json").exists():
        (out / "checkpoint.json").unlink()
    t0 = time.perf_counter()
    say(f"problem {problem.title}: drawing scenarios; compiling the batched rollout and its gradient (first step)")
    res, programs = _gradient(problem, setting, settings, family, out, log)
    grad_wall = time.perf_counter() - t0
    ctx = res.context
    paper_raw = loop.initial_raw(setting, family)
    tuned_raw = jnp.asarray(res.best_raw)
    evaluate_on = programs["evaluate_on"]
    train_eval = functools.partial(evaluate_on, scenarios=ctx.sets.train)
    heldout_eval = functools.partial(evaluate_on, scenarios=ctx.sets.heldout)

    train, held, ho_ok, ho_m = _evaluate(train_eval, heldout_eval, paper_raw, tuned_raw, say, log)
    # the baselines keep the gradient's requirement: a candidate that misses it is not simulated
    feasible = None if ctx.kept is None else baselines.requirement_check(ctx.kept)
    base, runs, match = _baselines(
        settings, family, train_eval, heldout_eval, paper_raw, res.history, say, log, feasible
    )
    best, best_raw = _best_heldout(base, runs, held[1], tuned_raw)
    if best["method"] != "gradient":
        log(
            f"{best['method']} (seed {best['seed']}) ends below the gradient on held-out loss "
            f"({best['heldout_loss']:.5g} vs {held[1]:.5g}): its gains are in {BEST_FILE}; gains.json and the "
            "radii are the gradient's"
        )
    say("certifying the initial and the tuned gains (Lemma 2, exact map" + (", falsifier)" if falsify else ")"))
    radius = _radii(setting, settings, family, res, paper_raw, tuned_raw, falsify)
    say("writing gains, history, figures and summary")
    _write(out, problem, setting, family, res, runs, paper_raw, tuned_raw, programs, radius)
    files.write_json(out / BEST_FILE, gains_file_dict(family.gains(best_raw), setting.ctrl))
    report = TuneReport(
        problem, setting, settings, family, res, paper_raw, tuned_raw, train, held, ho_ok, ho_m, base, match,
        radius, best, grad_wall, time.perf_counter() - t0,
    )  # fmt: skip
    report.write_summary(out)
    return report


BEST_FILE = "gains_best_heldout.json"
"""The gains with the lowest held-out loss of every method and seed (the gradient's included)."""


def _best_heldout(base: dict, runs: dict, heldout_tuned: float, tuned_raw):
    """The method and seed whose gains have the lowest held-out loss: the gradient's unless a
    baseline's seed ends below it (CMA-ES did on the car, issue 58). ``(report, raw parameters)``."""
    best = {"method": "gradient", "seed": None, "heldout_loss": heldout_tuned, "file": BEST_FILE}
    raw = tuned_raw
    for name, rep in base.items():
        for per, r in zip(rep["per_seed"], runs[name]):
            if per["best_heldout_loss"] < best["heldout_loss"]:
                best = {
                    "method": name,
                    "seed": per["seed"],
                    "heldout_loss": per["best_heldout_loss"],
                    "file": BEST_FILE,
                }
                raw = jnp.asarray(r.best_raw)
    return best, raw


def _gradient(problem, setting, settings, family, out: Path, log):
    """The gradient loop, with the later programs compiled on a second thread: ``(result, programs)``."""
    programs = {}
    second = ThreadPoolExecutor(max_workers=1)

    def prepare(ctx):
        # the programs of the validation, the evaluations and the figure, compiled on a second
        # thread while this one compiles the gradient (XLA compiles without the GIL)
        raw0 = loop.initial_raw(setting, family)
        loop.validation_loss.trace(raw0, ctx.sets.validation, setting, family, ctx.weights)
        programs.update(_programs(ctx))
        programs["ready"] = [second.submit(_warm_up, programs, ctx, raw0), second.submit(_preload)]

    run_id = problem.fingerprint() + repr(tuple(settings.optimizer))
    try:
        res = loop.tune(
            setting,
            family,
            settings.optimizer.build(settings.steps),
            steps=settings.steps,
            scenarios=settings.scenarios,
            loss=settings.loss,
            stopping=settings.stopping,
            seed=settings.seed,
            out_dir=out,
            run_id=run_id,
            log=log,
            on_built=prepare,
            requirement=settings.requirement,
        )
        for done in programs["ready"]:
            done.result()  # their errors are raised here
    except BaseException:
        second.shutdown(wait=False, cancel_futures=True)  # a failed run does not wait for them
        raise
    second.shutdown()
    return res, programs


def _evaluate(train_eval, heldout_eval, paper_raw, tuned_raw, say, log):
    """The initial and the tuned gains on the training and held-out scenarios:
    ``((train initial, train tuned), (held-out initial, held-out tuned), held-out validity, metrics)``."""
    say("evaluating the initial and the tuned gains on the held-out scenarios")
    both = np.stack([np.asarray(paper_raw), np.asarray(tuned_raw)])
    tr_paper, tr_tuned = (float(v) for v in train_eval(both))
    ho, (ho_ok, ho_m) = heldout_eval(both, with_aux=True)
    ho_paper, ho_tuned = (float(v) for v in ho)  # +inf where a set's objective is not finite
    log(
        f"held-out loss: initial gains {ho_paper:.5g}, tuned {ho_tuned:.5g} (ratio {ho_paper / ho_tuned:.2f}); "
        f"singular events {int(np.sum(ho_m.singular[0]))} -> {int(np.sum(ho_m.singular[1]))}"
    )
    return (tr_paper, tr_tuned), (ho_paper, ho_tuned), ho_ok, ho_m


def _write(out: Path, problem, setting, family, res, runs, paper_raw, tuned_raw, programs, radius) -> None:
    """Write ``gains.json``, ``history.json`` and the figures."""
    files.write_json(out / "gains.json", gains_file_dict(family.gains(tuned_raw), setting.ctrl))
    files.write_json(
        out / "history.json",
        {
            "gradient": res.history,
            **{
                name: [
                    {"seed": r.seed, "best_so_far": r.best_so_far, "rollouts_per_candidate": r.rollouts_per_candidate}
                    for r in rs
                ]
                for name, rs in runs.items()
            },
        },
    )
    _figures(out, problem.title, setting, family, res.history, runs, paper_raw, tuned_raw, programs)
    if "initial" in radius:
        _radii_figure(out, problem.title, radius)


def baseline_budget(settings, family) -> int:
    """Rollouts of one baseline run (``budget`` times the gradient's); ValueError when that is less
    than one CMA-ES generation."""
    b = settings.baselines
    budget = int(round(b.budget * settings.steps * settings.scenarios.train))
    pop = b.population(family.size)
    if budget < pop * settings.scenarios.train:
        raise ValueError(
            f"[tune.baselines] budget = {b.budget} gives {budget} rollouts, less than one CMA-ES "
            f"generation ({pop} candidates x {settings.scenarios.train} scenarios); raise budget or steps, "
            "or lower cma_population"
        )
    return budget


def _baselines(settings, family, train_eval, heldout_eval, paper_raw, hist, say, log, feasible=None):
    """Random search and CMA-ES, every seed: ``(report, runs, gradient rollouts to match)``;
    ``feasible``: the requirement's check of a candidate (None: no requirement)."""
    b = settings.baselines
    budget = baseline_budget(settings, family)
    pop = b.population(family.size)
    runs, t_base = _baseline_runs(settings, family, train_eval, paper_raw, budget, pop, say, feasible)
    base, match = {}, {}
    for name, rs in runs.items():
        base[name], match[name] = _baseline_report(name, rs, heldout_eval, hist, budget, t_base[name], log)
    base["cma_es"].update(
        population=pop,
        sigma0=b.cma_sigma,
        implementation="cmaes (CyberAgent) CMA, ask/tell; candidates simulated in batched jit calls",
    )
    base["random_search"]["box"] = (
        f"log-uniform: rates in [{b.search_low}, {b.search_high}] 1/s, dampings in "
        f"[{max(0.3, 1.01 * family.min_damping):g}, 3], every knot independently"
    )
    return base, runs, match


def _baseline_runs(settings, family, train_eval, paper_raw, budget: int, pop: int, say, feasible=None):
    """Run random search and CMA-ES for every seed: ``(runs by name, wall time by name)``; a
    candidate ``feasible`` rejects scores +inf, unsimulated (and is charged its rollouts)."""
    b = settings.baselines
    runs = {"random_search": [], "cma_es": []}
    t_base = {"random_search": 0.0, "cma_es": 0.0}
    n_train = settings.scenarios.train
    for k in range(b.seeds):
        seed = settings.seed * 1000 + k
        kept = "" if feasible is None else ", each candidate checked against the requirement first"
        say(f"baselines, seed {k + 1}/{b.seeds}: random search and CMA-ES, {budget} rollouts each{kept}")
        t1 = time.perf_counter()
        runs["random_search"].append(
            baselines.random_search(
                family,
                train_eval,
                paper_raw,
                budget_rollouts=budget,
                n_train=n_train,
                seed=seed,
                low=b.search_low,
                high=b.search_high,
                feasible=feasible,
            )
        )
        t2 = time.perf_counter()
        runs["cma_es"].append(
            baselines.cma_es(
                family,
                train_eval,
                paper_raw,
                budget_rollouts=budget,
                n_train=n_train,
                seed=seed,
                population=pop,
                sigma=b.cma_sigma,
                feasible=feasible,
            )
        )
        t_base["random_search"] += t2 - t1
        t_base["cma_es"] += time.perf_counter() - t2
    return runs, t_base


def _baseline_report(name: str, rs, heldout_eval, hist, budget: int, wall: float, log):
    """One baseline's report over its seeds and the gradient rollouts to match it (None: never)."""
    held = np.asarray(heldout_eval(np.stack([np.asarray(r.best_raw) for r in rs])), float)
    # a seed whose every candidate missed the requirement has no gains to report (never the best)
    held = np.where(np.isfinite([r.best_loss for r in rs]), held, np.inf)
    reach = [baselines.rollouts_to_reach(hist, r.best_loss) for r in rs]
    rep = {
        "best_loss": float(np.median([r.best_loss for r in rs])),
        "best_heldout_loss": float(np.median(held)),
        "rollouts_to_best": float(np.median([r.rollouts_to_best for r in rs])),
        "statistic": f"median over {len(rs)} seeds",
        "per_seed": [
            {
                "seed": r.seed,
                "best_loss": r.best_loss,
                "best_heldout_loss": float(h),
                "rollouts_to_best": r.rollouts_to_best,
                "rollouts": r.rollouts,
                "gradient_rollouts_to_match": m,
            }
            for r, h, m in zip(rs, held, reach)
        ],
        "rollouts_budget": budget,
        "wall_time_s": wall,
    }
    med = float(np.median([np.inf if m is None else m for m in reach]))  # a seed never matched counts as inf
    match = med if np.isfinite(med) else None
    ratio = float(np.median([r.rollouts_to_best / m if m is not None else 0.0 for r, m in zip(rs, reach)]))
    rep["rollout_ratio_baseline_over_gradient"] = ratio if match is not None else None
    rep["seeds_matched_by_gradient"] = sum(m is not None for m in reach)
    log(
        f"{name}: median best train loss {rep['best_loss']:.5g} after {rep['rollouts_to_best']:.0f} "
        f"rollouts, held-out {rep['best_heldout_loss']:.5g}; gradient reached it after {match} "
        f"rollouts ({rep['seeds_matched_by_gradient']}/{len(reach)} seeds)"
    )
    return rep, match


def _radii(setting, settings, family, res, paper_raw, tuned_raw, falsify: bool):
    """Every radius of the initial and the tuned gains (:func:`wmrjax.tune.certified.radii`), the
    requirement and how it was kept; None where the problem has no certificate (a static law,
    a random reference family) with the reason."""
    try:
        certified.check(setting, family)
    except ValueError as err:
        return {"skipped": str(err)}
    req, kept = settings.requirement, res.context.kept
    eps = req.eps if req is not None else certified.DEFAULT_EPS
    kw = dict(eps=eps, falsify=falsify, seed=settings.seed)
    out = {
        "initial": certified.radii(setting, family.gains(paper_raw), **kw),
        "tuned": certified.radii(setting, family.gains(tuned_raw), **kw),
        "problem_loop": certified.problem_loop(setting, req),
    }
    if setting.plant:  # the problem loop's proved radius of both gains, where a proof covers the plant
        out["problem_certificate"] = {
            k: certified.problem_radii(setting, family.gains(raw), eps=eps)
            for k, raw in (("initial", paper_raw), ("tuned", tuned_raw))
        }
    if kept is not None:
        out["requirement"] = _requirement_block(req, kept, res, out["tuned"], tuned_raw)
    return out


def _requirement_block(req, kept, res, tuned: dict, tuned_raw) -> dict:
    """How the requirement was kept: the radius it is on (what it covers, its kind), the run's
    smallest accepted radius and the tuned gains' (plain JSON)."""
    rad, hist = kept.radius, res.history
    held = rad.value(jnp.asarray(tuned_raw))
    block = {
        **req._asdict(),
        "required_radius": kept.required,
        "measured_by": rad.label,
        "covers": list(rad.covers),
        "not_covered": list(rad.not_covered),
        "kind": rad.kind,
        "initial_gains_radius": kept.initial,
        "smallest_radius_of_the_run": float(np.min([h["radius"] for h in hist if "radius" in h])),
        "tuned_radius": held,
        # the exact map keeps its attained radius; its proved bound is certify's
        "tuned_radius_lower_bound": held
        if rad.kind == certified.Kind.PROVED
        else tuned[f"exact_map_{req.slice}"].get("lower_bound"),
        "held": bool(held >= kept.required),
        "steps_projected": sum(1 for h in hist if h.get("halvings") == -1),
        "steps_halved": sum(1 for h in hist if h.get("halvings", 0) > 0),
    }
    if rad.detail is not None:
        block["tuned_bounds"] = rad.detail(jnp.asarray(tuned_raw))
        block["steps_bound_by"] = {
            k: sum(1 for h in hist if h.get("radius_bound_by") == k)
            for k in ("exact_map", "saturation_free", "held_reach")
        }
    return block


def _summary(r: TuneReport) -> dict:
    """``summary.json`` but the best held-out gains and the wall time."""
    problem, setting, settings, family, res = r.problem, r.setting, r.settings, r.family, r.result
    paper_raw, tuned_raw, train, heldout, ho_ok = r.initial_raw, r.tuned_raw, r.train_loss, r.heldout_loss, r.heldout_ok
    hist = res.history
    m_paper, m_tuned = (jax.tree_util.tree_map(lambda x: x[i], r.heldout_metrics) for i in (0, 1))
    ho_paper, ho_tuned = heldout
    ctrl = setting.ctrl
    return {
        "experiment": "tuning",
        "problem_name": problem.title,
        "problem": problem.resolved(),
        "tune": settings.as_dict(),
        "controller": f"{type(ctrl).__name__} of type {ctrl.robot.name}, {ctrl.level} level",
        **gains_owner(ctrl),  # whose gains, as gains.json says it: this summary is a gains file too
        "n_parameters": family.size,
        "gain_family": (
            "gain schedule, knots at " + ", ".join(f"{t:g}" for t in family.knots) + " s"
            if family.knots
            else "constant"
        )
        + (", shared by the outputs" if family.shared else ", per output"),
        "initial_gains": _gains_report(family, paper_raw),
        "tuned_gains": {
            **_gains_report(family, tuned_raw),
            "selected_by": "best validation loss among evaluations",
            "file": "gains.json",
        },
        "train_loss": {
            "initial": hist[0]["train_loss"],
            "final": hist[-1]["train_loss"],
            "paper_gains": train[0],
            "tuned": train[1],
        },
        "heldout_loss": {
            "paper_gains": ho_paper,
            "tuned": ho_tuned,  # null ratio where one is not finite
            "ratio_paper_over_tuned": ho_paper / ho_tuned if np.isfinite([ho_paper, ho_tuned]).all() else None,
        },
        "heldout_terms": {
            k: {
                f: float(np.mean(np.asarray(getattr(m, f))[np.asarray(m.valid)]))
                for f in ("tracking", "effort", "saturation", "barrier")
            }
            for k, m in (("paper_gains", m_paper), ("tuned", m_tuned))
        },
        "singularity_events": {"paper_gains": int(np.sum(m_paper.singular)), "tuned": int(np.sum(m_tuned.singular))},
        "failed_heldout_scenarios": {"paper_gains": int(np.sum(~ho_ok[0])), "tuned": int(np.sum(~ho_ok[1]))},
        "excluded_training_scenarios": res.excluded,
        "rollouts": res.rollouts,
        "rollout_counting": "one rollout = one scenario simulated once; a gradient step over B scenarios counts B "
        "(its extra cost is in gradient_wall_time_s); held-out and validation runs are not counted",
        "objective": f"mean loss of the valid scenarios + {loop.FAILURE_PENALTY} x fraction failed (+ certificate term)",
        "baselines": r.baselines,
        "rollouts_to_match": r.rollouts_to_match,
        "steps": len(hist),
        "stopped_early": res.stopped_early,
        "gradient_wall_time_s": r.gradient_wall_time_s,
        "tuning_wall_time_s_including_compile": res.wall_time_s,
        "radii": r.radii,
    }


def _programs(ctx) -> dict:
    """The functions of a run after its gradient loop.

    Returns:
      A dict: ``evaluate_on`` (:func:`wmrjax.tune.baselines.candidate_evaluator` of the training
      objective, with per-scenario validity and metrics as aux: the training-set evaluations,
      the held-out report and the baselines; +inf where an objective is not finite),
      ``trajectories(gains) -> (output positions (n, 2), position errors (n, 2))`` of held-out
      scenario 0 at the controller's samples, that ``scenario`` and its sample times ``t`` [s].
    """
    setting, family, weights, cert = ctx.setting, ctx.family, ctx.weights, ctx.certificate

    def objective(raw, scen):
        val, ok, m = loop.mean_loss(raw, scen, setting, family, weights)
        return loop.objective(val, ok) + loop.certificate_term(family, raw, cert), (ok, m)

    sc = jax.tree_util.tree_map(lambda x: np.asarray(x)[0], ctx.sets.heldout)  # on the host: no per-leaf program
    every = setting.steps_per_sample or 1
    t = np.arange(setting.n_steps // every) * every * setting.dt

    @functools.partial(jax.jit, compiler_options=loop.QUICK_COMPILE)
    def trajectories(gains):  # the tracked point and its position error at the samples
        _, tr, params = rollout(setting, gains, sc, trajectory=True)

        zs = law_state(setting.system(), jax.tree_util.tree_map(lambda x: x[:-1], tr.state))
        err = jax.vmap(lambda tt, z: setting.ctrl.error(tt, z, params)[0])(jnp.asarray(t), zs)
        return zs[:, :2], err

    # one program for every evaluation after the gradient's (the training and held-out sets
    # have the same size in the default problems; a set of another size compiles its own)
    return {
        "evaluate_on": baselines.candidate_evaluator(objective, family.shape, compiler_options=loop.LOOP_COMPILE),
        "trajectories": trajectories,
        "scenario": sc,
        "t": t,
    }


def _warm_up(programs, ctx, raw) -> None:
    """Compile the validation program and ``programs`` by calling each once (an evaluation
    runs one chunk of 16 candidates)."""
    loop.validation_loss(raw, ctx.sets.validation, ctx.setting, ctx.family, ctx.weights)
    programs["evaluate_on"](np.asarray(raw)[None], ctx.sets.train)
    size = lambda sc: jax.tree_util.tree_leaves(sc)[0].shape[0]
    if size(ctx.sets.heldout) != size(ctx.sets.train):
        programs["evaluate_on"](np.asarray(raw)[None], ctx.sets.heldout)  # a set of another size: its own program
    programs["trajectories"](ctx.family.gains(raw))


def _preload() -> None:
    """Import what the end of a run needs (cmaes, which imports scipy.stats, and matplotlib: slow
    imports) on the second thread, while the main one runs the gradient loop."""
    import cmaes  # noqa: F401

    files.headless_pyplot()


def _gains_report(family, raw):
    pos = np.asarray(family.positive(raw))
    params = dict(zip(family.names(), pos.tolist())) if family.shared and not family.knots else pos.tolist()
    return {
        "parameterization": family.parameterization,
        "shared_across_outputs": family.shared,
        "knots_s": list(family.knots),
        "parameter_names": family.names(),
        "parameters": params,
        "coefficients_k0_to_kr-1": np.asarray(family.coefficients(raw)).tolist(),
        "closed_loop_poles_re_im": family.closed_loop_poles(raw),
    }


def _band(runs):
    """(rollouts, median, low, high) of the best-so-far curves of several seeds."""
    n = min(len(r.best_so_far) for r in runs)
    curves = np.stack([np.asarray(r.best_so_far[:n]) for r in runs])
    x = (np.arange(n) + 1) * runs[0].rollouts_per_candidate
    return x, np.median(curves, axis=0), curves.min(axis=0), curves.max(axis=0)


def _figures(out, title, setting, family, hist, runs, paper_raw, tuned_raw, programs):
    plt = files.headless_pyplot()
    fig, ax = plt.subplots(figsize=(6.8, 4.3))
    ax.semilogy([h["rollouts"] for h in hist], [h["train_loss"] for h in hist], "C0", label="gradient (train)")
    va = [(h["rollouts"], h["validation_loss"]) for h in hist if "validation_loss" in h]
    ax.semilogy(*zip(*va), "C0o--", ms=3, label="gradient (validation)")
    for (name, rs), c in zip(runs.items(), ("C3", "C2")):
        x, med, lo, hi = _band(rs)
        ax.semilogy(x, med, c, label=f"{name.replace('_', ' ')} (best so far, median of {len(rs)} seeds)")
        ax.fill_between(x, lo, hi, color=c, alpha=0.2, lw=0)
    ax.set_xscale("log")
    ax.set_xlabel("rollouts (scenario simulations)")
    ax.set_ylabel("training objective")
    ax.set_title(f"{title}: loss vs rollouts (band: min-max over seeds)")
    ax.grid(alpha=0.3, which="both")
    ax.legend(fontsize=7)
    files.write_png(fig, out / "loss.png")
    plt.close(fig)

    ts = np.linspace(0.0, setting.t_final, 201)
    fig, axs = plt.subplots(1, family.r, figsize=(3.6 * family.r, 3.4), squeeze=False)
    names = family.names()
    # one program for both schedules (a jit per schedule compiled twice)
    schedule_at = jax.jit(lambda gains, ts: jax.vmap(gains.parameters_at)(ts))
    for raw, lab, ls in ((paper_raw, "initial", "--"), (tuned_raw, "tuned", "-")):
        gains = family.gains(raw)
        if family.knots:
            pos = np.asarray(schedule_at(gains, jnp.asarray(ts)))  # (T, m, r)
        else:  # (T, 1 or m, r)
            one = np.asarray(family.positive(raw)).reshape(-1, family.r)
            pos = np.broadcast_to(one, (len(ts),) + one.shape)
        for j in range(family.r):
            for i in range(pos.shape[1]):
                axs[0, j].plot(ts, pos[:, i, j], f"C{i}{ls}", lw=1.2, label=f"{lab}, output {i + 1}")
    for j in range(family.r):
        unit = "" if names[j].startswith("zeta") else " [1/s]"
        axs[0, j].set_title(names[j] + unit)
        axs[0, j].set_xlabel("t [s]")
        axs[0, j].grid(alpha=0.3)
        if family.knots:
            for tk in family.knots:
                axs[0, j].axvline(tk, color="0.7", lw=0.6)
    axs[0, 0].legend(fontsize=6)
    fig.suptitle(f"{title}: gains over time (grey: knots)" if family.knots else f"{title}: gains")
    fig.tight_layout()
    files.write_png(fig, out / "schedule.png")
    plt.close(fig)

    sc, t = programs["scenario"], programs["t"]
    fig, axs = plt.subplots(1, 2, figsize=(11, 4.4))

    ref = R.Reference(sc.inputs.reference, sc.inputs.heading_offset, setting.reference.path, setting.reference.name)
    pos_ref = np.asarray(jax.jit(jax.vmap(ref.position))(t))
    axs[0].plot(pos_ref[:, 0], pos_ref[:, 1], "k--", lw=1.2, label="reference")
    for raw, lab, c in ((paper_raw, "initial gains", "C3"), (tuned_raw, "tuned", "C0")):
        xy, err = (np.asarray(x) for x in programs["trajectories"](family.gains(raw)))
        axs[0].plot(xy[:, 0], xy[:, 1], c, lw=1.2, label=lab)
        axs[1].semilogy(t, np.maximum(np.hypot(err[:, 0], err[:, 1]), 1e-8), c, label=lab)
    axs[0].set_xlabel("x [m]")
    axs[0].set_ylabel("y [m]")
    axs[0].axis("equal")
    axs[0].set_title(f"{title}: one held-out scenario (saturation, mismatch, noise)")
    axs[1].set_xlabel("t [s]")
    axs[1].set_ylabel("output position error [m]")
    for a in axs:
        a.grid(alpha=0.3)
        a.legend(fontsize=8)
    fig.tight_layout()
    files.write_png(fig, out / "trajectories.png")
    plt.close(fig)


def _radii_figure(out, title, radii: dict) -> None:
    """``radii.png``: every radius of the initial and the tuned gains side by side, the
    falsified ones and the requirement marked."""
    plt = files.headless_pyplot()
    rows = [(f"lemma2_{k}", v["label"]) for k, v in radii["initial"]["lemma2"].items()]
    rows += [(f"exact_map_{b}", f"exact map ({b})") for b in certified.SLICES]

    def value(which, key, field="radius"):
        d = radii[which]
        block = d["lemma2"].get(key[len("lemma2_") :]) if key.startswith("lemma2_") else d[key]
        return np.nan if block is None or block.get(field) is None else block[field]

    fig, ax = plt.subplots(figsize=(7.4, 0.55 * len(rows) + 1.6))
    y = np.arange(len(rows))
    for dy, which, c in ((-0.18, "initial", "C3"), (0.18, "tuned", "C0")):
        ax.barh(y + dy, [value(which, k) for k, _ in rows], height=0.34, color=c, label=f"{which} gains")
        ax.plot([value(which, k, "falsified") for k, _ in rows], y + dy, "k|", ms=12)
    req = radii.get("requirement")
    if req is not None:
        ax.axvline(
            req["required_radius"],
            color="C2",
            ls="--",
            label=f"required ({req['slice']} slice): {req['required_radius']:.3g}",
        )
    ax.set_yticks(y, [lab for _, lab in rows], fontsize=7)
    ax.invert_yaxis()
    ax.set_xlabel("radius of certified initial errors [m, m/s]  (|: falsified, an upper bound)")
    ax.set_title(f"{title}: certified radii, eps = {radii['initial']['eps']:g}", fontsize=10)
    ax.grid(alpha=0.3, axis="x")
    ax.legend(fontsize=7)
    fig.tight_layout()
    files.write_png(fig, out / "radii.png")
    plt.close(fig)
