r"""Tune the linearizing controller's gains by gradient descent through the simulator, against
random search and CMA-ES on the same terms.

    python -m tuning PROBLEM.toml --out results/my_problem         # any problem file with [tune]
    python -m tuning --problem car_schedule --out results/car_schedule

A problem file (:mod:`wmrjax.problem`) says the robot, the path, the plant and the initial
errors; its ``[tune]`` section (:mod:`tuning.config`) the gain family, the loss, the scenario
counts, the optimizer, early stopping and the baselines. The shipped problems
(``tuning/problems/*.toml``): ``section_6_1`` (default), ``car_schedule``, ``torque_2_1``.
Every option below overrides the file's value.

Writes ``gains.json`` (the tuned gains: ``[gains] file`` of any problem reads it),
``summary.json`` (with the whole resolved problem and every certified radius of the initial
and tuned gains), ``history.json``, ``checkpoint.json`` (a killed run resumes from it),
``loss.png``, ``schedule.png``, ``trajectories.png`` and, where the problem has a certificate,
``radii.png``.
"""

from __future__ import annotations

import argparse
import functools
import sys
import time
from concurrent.futures import ThreadPoolExecutor
from pathlib import Path

from wmrjax_cli import files

_S = "(default: the file's)"


def parser():
    from wmrjax_cli import options

    p = options.parser(__doc__.splitlines()[0], "results/tuning")
    _add_problem_options(p)
    _add_tuning_options(p)
    _add_plant_options(p)
    _add_loss_and_baseline_options(p)
    _add_requirement_and_run_options(p)
    return p


def _add_problem_options(p) -> None:
    """The problem file or shipped problem, the robot, the task, the reference and the initial errors."""
    from tuning.problems import PROBLEMS
    from wmrjax_cli import options

    S = _S
    p.add_argument("file", type=Path, nargs="?", default=None, help="a problem file (TOML) with a [tune] section")
    p.add_argument(
        "--problem",
        default=None,
        choices=sorted(PROBLEMS),
        help="a shipped problem instead of a file (default: section_6_1)",
    )
    p.add_argument("--robot", default=None, help=f"robot type: (3,0), (2,0), (2,1), (1,1) or (1,2) {S}")
    p.add_argument(
        "--task",
        default=None,
        choices=["posture", "point"],
        help=f"posture: dynamic law (restricted types) or Prop 3 (3,0); point: static Table 3 law {S}",
    )
    p.add_argument(
        "--level", default=None, choices=["velocity", "torque"], help=f"velocity (model 5) or torque (Lemma 1) {S}"
    )
    p.add_argument(
        "--reference",
        default=None,
        help=f"a reference family (paper_62, circle, figure_eight, line, random_smooth, ...) or a CSV file of "
        f"samples t, x, y {S}",
    )
    p.add_argument("--heading-offset", type=options.finite, default=None, help=f"reference heading offset [rad] {S}")
    p.add_argument(
        "--geometry",
        type=options.finite,
        nargs=3,
        default=None,
        metavar=("L", "E", "DELTA"),
        help=f"nominal geometry the controller uses [m, m, rad] {S}",
    )
    p.add_argument(
        "--ic-position",
        type=options.nonnegative,
        default=None,
        help="initial position errors x, y uniform in +-A [m] (sets the [initial] box)",
    )
    p.add_argument(
        "--ic-velocity",
        type=options.nonnegative,
        default=None,
        help="initial velocity errors vx, vy uniform in +-B [m/s] (output space)",
    )


def _add_tuning_options(p) -> None:
    """The scenario counts, the optimizer and the gain family."""
    from wmrjax_cli import options

    S = _S
    p.add_argument("--n-train", type=options.count, default=None, help=f"training scenarios per step {S}")
    p.add_argument(
        "--n-validation", type=options.count, default=None, help=f"validation scenarios (early stopping, selection) {S}"
    )
    p.add_argument("--n-heldout", type=options.count, default=None, help=f"held-out scenarios (reported only) {S}")
    p.add_argument("--steps", type=options.count, default=None, help=f"optimizer steps {S}")
    p.add_argument(
        "--learning-rate",
        type=options.positive,
        default=None,
        help=f"Adam learning rate (on the softplus-unconstrained parameters) {S}",
    )
    p.add_argument(
        "--poles-init",
        type=options.positive,
        default=None,
        help=f"initial pole magnitude [1/s] (the paper's: 1; sets [gains] poles) {S}",
    )
    p.add_argument("--per-axis", action="store_true", default=None, help="one set of gains per output")
    p.add_argument(
        "--resample",
        action=argparse.BooleanOptionalAction,
        default=None,
        help=f"fresh training scenarios every gradient step (stochastic gradient) {S}",
    )
    p.add_argument(
        "--knots",
        type=options.nonnegative_int,
        default=None,
        help=f"gain schedule with this many knots uniform on [0, t_final] (0: constant gains) {S}",
    )
    p.add_argument(
        "--knot-times",
        type=options.nonnegative,
        nargs="+",
        default=None,
        help="explicit knot times of the gain schedule [s] (overrides --knots)",
    )
    p.add_argument(
        "--min-damping", type=options.nonnegative, default=None, help=f"floor of every damping zeta (in [0, 1)) {S}"
    )
    p.add_argument(
        "--parameterization",
        default=None,
        choices=["damping", "poles"],
        help=f"damping: (omega, zeta) factors (real or complex poles); poles: real poles only {S}",
    )


def _add_plant_options(p) -> None:
    """The plant's mismatch, actuator limits, noise, controller period and horizon."""
    from wmrjax_cli import options

    S = _S
    p.add_argument(
        "--mismatch",
        type=options.fraction,
        default=None,
        help=f"+- relative input-scale/geometry error of the plant per scenario (in [0, 1)) {S}",
    )
    p.add_argument(
        "--input-limit",
        type=options.limit,
        nargs="*",
        default=None,
        help="plant actuator limits per input [m/s, rad/s; per s^2 at torque level] (inf: none; no "
        f"values: no saturation) {S}",
    )
    p.add_argument(
        "--noise-std",
        type=options.nonnegative,
        nargs="*",
        default=None,
        help=f"measurement noise std of x, y [m] and theta [rad] (and steering angles [rad]) {S}",
    )
    p.add_argument(
        "--control-dt", type=options.positive, default=None, help=f"controller period (zero-order hold) [s] {S}"
    )
    p.add_argument("--t-final", type=options.positive, default=None, help=f"horizon of every scenario [s] {S}")


def _add_loss_and_baseline_options(p) -> None:
    """The loss weights, the baselines and the seed."""
    from tuning.losses import LossWeights
    from wmrjax_cli import options

    S = _S
    for f in LossWeights._fields:
        p.add_argument(
            f"--w-{f}", type=options.nonnegative, default=None, help=f"weight of the {f} loss term (>= 0) {S}"
        )
    p.add_argument("--baseline-seeds", type=options.count, default=None, help=f"seeds of each baseline {S}")
    p.add_argument(
        "--baseline-budget",
        type=options.positive,
        default=None,
        help=f"baseline rollouts as a multiple of the gradient's {S}",
    )
    p.add_argument(
        "--cma-population",
        type=options.nonnegative_int,
        default=None,
        help=f"CMA-ES population (0: 4 + floor(3 ln n)) {S}",
    )
    p.add_argument(
        "--seed", type=options.seed, default=None, help=f"PRNG seed of the scenarios (and the baselines) {S}"
    )


def _add_requirement_and_run_options(p) -> None:
    """The certified-radius requirement, the falsifier and a fresh start."""
    S = _S
    p.add_argument(
        "--require-radius",
        type=_required,
        default=None,
        metavar="R",
        help="keep the exact-map radius of initial errors certified >= R throughout [m, m/s]; 'initial': "
        f"the initial gains', 'box': the [initial] box's half-diagonal (sets [tune.requirement]) {S}",
    )
    p.add_argument(
        "--require-slice",
        default=None,
        choices=["full", "position"],
        help=f"the requirement's slice of initial errors {S}",
    )
    p.add_argument(
        "--falsify",
        action="store_true",
        help="also falsify the initial and tuned gains' exact-map radii by rollouts (slower)",
    )
    p.add_argument("--fresh", action="store_true", help="ignore (delete) an existing checkpoint in --out")


def _required(text: str):
    """``--require-radius``: a radius >= 0, ``initial`` or ``box``."""
    if text in ("initial", "box"):
        return text
    from wmrjax_cli import options

    return options.nonnegative(text)


# option -> dotted key of the problem file it sets
_KEYS = {
    "robot": "controller.robot",
    "level": "controller.level",
    "heading_offset": "reference.heading_offset",
    "n_train": "tune.scenarios.train",
    "n_validation": "tune.scenarios.validation",
    "n_heldout": "tune.scenarios.heldout",
    "steps": "tune.steps",
    "learning_rate": "tune.optimizer.learning_rate",
    "poles_init": "gains.poles",
    "knots": "tune.family.knots",
    "parameterization": "tune.family.parameterization",
    "mismatch": "tune.scenarios.mismatch",
    "control_dt": "plant.control_period",
    "t_final": "simulation.t_final",
    "baseline_seeds": "tune.baselines.seeds",
    "baseline_budget": "tune.baselines.budget",
    "cma_population": "tune.baselines.cma_population",
    "seed": "tune.seed",
    "min_damping": "tune.family.min_damping",
    "resample": "tune.scenarios.resample",
    "require_radius": "tune.requirement.radius",
    "require_slice": "tune.requirement.slice",
}


def problem_from_args(a):
    """The problem file (or shipped problem) with every option given on the command line applied."""
    from tuning.losses import LossWeights
    from tuning.problems import problem_file
    from wmrjax.problem import Problem

    if a.file is not None and a.problem is not None:
        raise ValueError("give a problem file or --problem NAME, not both")
    path = a.file if a.file is not None else problem_file(a.problem or "section_6_1")
    problem = Problem.load(path)
    values = {key: getattr(a, k) for k, key in _KEYS.items() if getattr(a, k) is not None}
    if a.geometry is not None:
        values.update({f"geometry.{k}": v for k, v in zip(("L", "e", "delta"), a.geometry)})
    if a.input_limit is not None:
        values["plant.input_limit"] = list(a.input_limit) if a.input_limit else None
    if a.noise_std is not None:
        values["plant.noise_std"] = list(a.noise_std)
    if a.knot_times is not None:
        values["tune.family.knot_times"] = list(a.knot_times)
        values["tune.family.knots"] = None
    if a.per_axis:
        values["tune.family.shared"] = False
    if a.reference is not None:
        values.update(_reference_values(a.reference))
    values.update(_law_values(a, problem, values))
    box = {k: a.ic_position for k in ("x", "y")} if a.ic_position is not None else {}
    box |= {k: a.ic_velocity for k in ("vx", "vy")} if a.ic_velocity is not None else {}
    for k, v in box.items():
        values[f"initial.{k}"] = {"low": -v, "high": v}
    if box and "random" not in problem.data["initial"]:
        values["initial.random"] = {"count": 64, "seed": 0}
    for f in LossWeights._fields:
        if getattr(a, f"w_{f}") is not None:
            values[f"tune.loss.{f}"] = getattr(a, f"w_{f}")
    return problem.with_values(values) if values else problem


def _law_values(a, problem, values) -> dict:
    """``--task`` and ``--robot`` as before problem files: the point task (and type (3,0)) take a
    static law, whose initial errors are physical (the output box's x and y kept)."""
    import wmrjax as w

    if a.task is None and a.robot is None:
        return {}
    robot = w.robot_type(values.get("controller.robot", problem.data["controller"]["robot"])).name
    task = w.Task(a.task or problem.data["controller"].get("task", w.Task.POSTURE))
    law = "static" if task == w.Task.POINT or robot not in w.controllers.TABLE4 else "dynamic"  # (3,0): Prop 3
    out = {"controller.law": law, "controller.task": str(task)}
    ini = problem.data["initial"]
    if law == "static" and ini.get("space", "output") == "output":
        out["initial"] = {"space": "physical", **{k: v for k, v in ini.items() if k in ("random", "x", "y")}}
    return out


def _reference_values(text: str) -> dict:
    """``--reference``: a family name, or a CSV file of samples (t, x, y)."""
    from wmrjax import references as R

    if text in R.FAMILIES:
        return {"reference": {"family": text}}
    path = Path(text)
    if path.suffix.lower() == ".csv" or path.is_file():
        return {"reference": {"family": "samples", "file": str(path.resolve())}}
    raise ValueError(f"--reference: expected a family ({', '.join(R.FAMILIES)}) or a CSV file of samples, got {text!r}")


def run(problem, out: Path, fresh: bool = False, log=print, progress=None, falsify: bool = False) -> dict:
    """Tune, evaluate, run the baselines, write ``gains.json``, the figures and ``summary.json``;
    returns the summary (``falsify``: falsify the exact-map radii of the initial and tuned gains)."""
    import jax

    jax.config.update("jax_enable_x64", True)  # this entry point runs in float64
    import jax.numpy as jnp

    from tuning import config, loop

    say = progress or log
    setting = problem.setting("tuning")
    settings = config.read(problem.section("tune"), problem.section("certify"))
    family = settings.gain_spec(setting)
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
    base, runs, match = _baselines(settings, family, train_eval, heldout_eval, paper_raw, res.history, say, log)
    say("certifying the initial and the tuned gains (Lemma 2, exact map" + (", falsifier)" if falsify else ")"))
    radius = _radii(setting, settings, family, res, paper_raw, tuned_raw, falsify)
    summary = _summary(
        problem,
        setting,
        settings,
        family,
        res,
        paper_raw,
        tuned_raw,
        train,
        held,
        ho_ok,
        ho_m,
        base,
        match,
        radius,
        grad_wall,
    )
    say("writing gains, history, figures and summary")
    _write(out, problem, setting, family, res, runs, paper_raw, tuned_raw, programs, radius)
    summary["wall_time_s"] = time.perf_counter() - t0
    files.write_json(out / "summary.json", summary)
    return summary


def _gradient(problem, setting, settings, family, out: Path, log):
    """The gradient loop, with the later programs compiled on a second thread: ``(result, programs)``."""
    from tuning import loop

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
    import numpy as np

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
    from wmrjax.problem import gains_file_dict

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


def _baselines(settings, family, train_eval, heldout_eval, paper_raw, hist, say, log):
    """Random search and CMA-ES, every seed: ``(report, runs, gradient rollouts to match)``."""
    b = settings.baselines
    budget = baseline_budget(settings, family)
    pop = b.population(family.size)
    runs, t_base = _baseline_runs(settings, family, train_eval, paper_raw, budget, pop, say)
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


def _baseline_runs(settings, family, train_eval, paper_raw, budget: int, pop: int, say):
    """Run random search and CMA-ES for every seed: ``(runs by name, wall time by name)``."""
    from tuning import baselines

    b = settings.baselines
    runs = {"random_search": [], "cma_es": []}
    t_base = {"random_search": 0.0, "cma_es": 0.0}
    n_train = settings.scenarios.train
    for k in range(b.seeds):
        seed = settings.seed * 1000 + k
        say(f"baselines, seed {k + 1}/{b.seeds}: random search and CMA-ES, {budget} rollouts each")
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
            )
        )
        t_base["random_search"] += t2 - t1
        t_base["cma_es"] += time.perf_counter() - t2
    return runs, t_base


def _baseline_report(name: str, rs, heldout_eval, hist, budget: int, wall: float, log):
    """One baseline's report over its seeds and the gradient rollouts to match it (None: never)."""
    import numpy as np

    from tuning import baselines

    held = heldout_eval(np.stack([np.asarray(r.best_raw) for r in rs]))
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
    """Every radius of the initial and the tuned gains (:func:`tuning.certified.radii`), the
    requirement and how it was kept; None where the problem has no certificate (a static law,
    a random reference family) with the reason."""
    import numpy as np

    from tuning import certified

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
        "problem_loop": certified.problem_loop(setting),
    }
    if kept is not None:
        path = [h["radius"] for h in res.history if "radius" in h]
        tuned = out["tuned"][f"exact_map_{req.slice}"]
        held = tuned["radius"]  # the attained radius, the one the tuner keeps (differentiable)
        out["requirement"] = {
            **req._asdict(),
            "required_radius": kept.required,
            "measured_by": kept.radius.label,
            "covers": tuned["covers"],
            "initial_gains_radius": kept.initial,
            "smallest_radius_of_the_run": float(np.min(path)),
            "tuned_radius": held,
            "tuned_radius_lower_bound": tuned.get("lower_bound"),
            "held": bool(held >= kept.required),
            "steps_projected": sum(1 for h in res.history if h.get("halvings") == -1),
            "steps_halved": sum(1 for h in res.history if h.get("halvings", 0) > 0),
        }
    return out


def _summary(
    problem,
    setting,
    settings,
    family,
    res,
    paper_raw,
    tuned_raw,
    train,
    heldout,
    ho_ok,
    ho_m,
    base,
    match,
    radius,
    grad_wall,
) -> dict:
    import jax
    import numpy as np

    from tuning import loop
    from wmrjax.problem import gains_owner

    hist = res.history
    m_paper, m_tuned = (jax.tree_util.tree_map(lambda x: x[i], ho_m) for i in (0, 1))
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
        "baselines": base,
        "rollouts_to_match": match,
        "steps": len(hist),
        "stopped_early": res.stopped_early,
        "gradient_wall_time_s": grad_wall,
        "tuning_wall_time_s_including_compile": res.wall_time_s,
        "radii": radius,
    }


def _programs(ctx) -> dict:
    """The functions of a run after its gradient loop.

    Returns:
      A dict: ``evaluate_on`` (:func:`tuning.baselines.candidate_evaluator` of the training
      objective, with per-scenario validity and metrics as aux: the training-set evaluations,
      the held-out report and the baselines; +inf where an objective is not finite),
      ``trajectories(gains) -> (output positions (n, 2), position errors (n, 2))`` of held-out
      scenario 0 at the controller's samples, that ``scenario`` and its sample times ``t`` [s].
    """
    import jax
    import jax.numpy as jnp
    import numpy as np

    from tuning import baselines, loop
    from tuning.scenarios import rollout

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
        from wmrjax.problem import law_state

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
    import jax
    import numpy as np

    from tuning import loop

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


def _gains_report(spec, raw):
    import numpy as np

    pos = np.asarray(spec.positive(raw))
    params = dict(zip(spec.names(), pos.tolist())) if spec.shared and not spec.knots else pos.tolist()
    return {
        "parameterization": spec.parameterization,
        "shared_across_outputs": spec.shared,
        "knots_s": list(spec.knots),
        "parameter_names": spec.names(),
        "parameters": params,
        "coefficients_k0_to_kr-1": np.asarray(spec.coefficients(raw)).tolist(),
        "closed_loop_poles_re_im": spec.closed_loop_poles(raw),
    }


def _band(runs):
    """(rollouts, median, low, high) of the best-so-far curves of several seeds."""
    import numpy as np

    n = min(len(r.best_so_far) for r in runs)
    curves = np.stack([np.asarray(r.best_so_far[:n]) for r in runs])
    x = (np.arange(n) + 1) * runs[0].rollouts_per_candidate
    return x, np.median(curves, axis=0), curves.min(axis=0), curves.max(axis=0)


def _figures(out, title, setting, spec, hist, runs, paper_raw, tuned_raw, programs):
    import jax
    import jax.numpy as jnp
    import numpy as np

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
    fig, axs = plt.subplots(1, spec.r, figsize=(3.6 * spec.r, 3.4), squeeze=False)
    names = spec.names()
    # one program for both schedules (a jit per schedule compiled twice)
    schedule_at = jax.jit(lambda gains, ts: jax.vmap(gains.parameters_at)(ts))
    for raw, lab, ls in ((paper_raw, "initial", "--"), (tuned_raw, "tuned", "-")):
        gains = spec.gains(raw)
        if spec.knots:
            pos = np.asarray(schedule_at(gains, jnp.asarray(ts)))  # (T, m, r)
        else:  # (T, 1 or m, r)
            one = np.asarray(spec.positive(raw)).reshape(-1, spec.r)
            pos = np.broadcast_to(one, (len(ts),) + one.shape)
        for j in range(spec.r):
            for i in range(pos.shape[1]):
                axs[0, j].plot(ts, pos[:, i, j], f"C{i}{ls}", lw=1.2, label=f"{lab}, output {i + 1}")
    for j in range(spec.r):
        unit = "" if names[j].startswith("zeta") else " [1/s]"
        axs[0, j].set_title(names[j] + unit)
        axs[0, j].set_xlabel("t [s]")
        axs[0, j].grid(alpha=0.3)
        if spec.knots:
            for tk in spec.knots:
                axs[0, j].axvline(tk, color="0.7", lw=0.6)
    axs[0, 0].legend(fontsize=6)
    fig.suptitle(f"{title}: gains over time (grey: knots)" if spec.knots else f"{title}: gains")
    fig.tight_layout()
    files.write_png(fig, out / "schedule.png")
    plt.close(fig)

    sc, t = programs["scenario"], programs["t"]
    fig, axs = plt.subplots(1, 2, figsize=(11, 4.4))
    from wmrjax import references as R

    ref = R.Reference(
        sc.inputs["reference"], sc.inputs["heading_offset"], setting.reference.path, setting.reference.name
    )
    pos_ref = np.asarray(jax.jit(jax.vmap(ref.position))(t))
    axs[0].plot(pos_ref[:, 0], pos_ref[:, 1], "k--", lw=1.2, label="reference")
    for raw, lab, c in ((paper_raw, "initial gains", "C3"), (tuned_raw, "tuned", "C0")):
        xy, err = (np.asarray(x) for x in programs["trajectories"](spec.gains(raw)))
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
    import numpy as np

    plt = files.headless_pyplot()
    rows = [(f"lemma2_{k}", v["label"]) for k, v in radii["initial"]["lemma2"].items()]
    rows += [(f"exact_map_{b}", f"exact map ({b})") for b in ("full", "position")]

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


def main(argv=None) -> int:
    from wmrjax_cli import options

    p = parser()
    a = p.parse_args(argv)
    options.configure_xla()  # before JAX starts its backend
    import jax

    jax.config.update("jax_enable_x64", True)  # float64 from the first check on (run() sets it too)
    try:
        problem = problem_from_args(a)
        from tuning import config, loop

        setting = problem.setting("tuning")
        settings = config.read(problem.section("tune"), problem.section("certify"))
        family = settings.gain_spec(setting)
        loop.check(setting, family, settings.scenarios, settings.loss)
        if settings.requirement is not None:
            from tuning import certified

            certified.check(setting, family)
        baseline_budget(settings, family)
    except ValueError as e:
        p.error(str(e))
    s = options.work(
        p,
        a,
        lambda progress: run(problem, a.out, a.fresh, log=progress, falsify=a.falsify),
        hint=lambda msg: msg + "; or rerun with --fresh to start over" if "checkpoint" in msg else msg,
    )
    b = s["baselines"]
    print(
        f"{problem.title}: {s['n_parameters']} parameters; held-out loss initial {s['heldout_loss']['paper_gains']:.4g} "
        f"-> tuned {s['heldout_loss']['tuned']:.4g} (CMA-ES {b['cma_es']['best_heldout_loss']:.4g}, random search "
        f"{b['random_search']['best_heldout_loss']:.4g}); singular events {s['singularity_events']}; "
        f"gradient rollouts {s['rollouts']}, to match CMA-ES {s['rollouts_to_match']['cma_es']} (CMA-ES best after "
        f"{b['cma_es']['rollouts_to_best']:.0f}); {s['wall_time_s']:.1f} s"
    )
    for line in radius_change_lines(s["radii"]):
        print(line)
    print(
        f"wrote {a.out}/gains.json, summary.json, history.json, checkpoint.json, loss.png, schedule.png, "
        "trajectories.png" + (", radii.png" if "initial" in s["radii"] else "")
    )
    return 0


def radius_change_lines(radii: dict) -> list:
    """The certified radii of the initial and the tuned gains on the console, per slice, with the
    change in percent (a tuned loop can track better and be certified from a smaller region:
    that was only in summary.json and radii.png)."""
    if "initial" not in radii:
        return [f"certified radii: {radii.get('skipped', 'none')}"]
    lines = []
    for key, block in radii["initial"].items():
        if not key.startswith("exact_map_") or key not in radii["tuned"]:
            continue
        r0 = block.get("lower_bound", block["radius"])
        r1 = radii["tuned"][key].get("lower_bound", radii["tuned"][key]["radius"])
        change = f"{100.0 * (r1 - r0) / r0:+.0f} %" if r0 > 0 else "n/a"
        lines.append(
            f"certified radius ({key.removeprefix('exact_map_')} slice, exact map, nominal loop, proved): "
            f"initial {r0:.4g} -> tuned {r1:.4g} ({change})"
        )
    loop = radii.get("problem_loop")
    if loop is not None and not loop["covered"]:
        lines.append(f"note: {loop['note']}")
    return lines


if __name__ == "__main__":
    sys.exit(main())
