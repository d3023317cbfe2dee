r"""Tune the linearizing controller's gains by gradient descent through the simulator, against
random search and CMA-ES on the same terms.

    wmrjax tune PROBLEM.toml --out results/my_problem         # any problem file with [tune]
    wmrjax tune --problem car_schedule --out results/car_schedule

A problem file (:mod:`wmrjax.problem`) says the robot, the path, the plant and the initial
errors; its ``[tune]`` section (:mod:`wmrjax.tune.config`) the gain family, the loss, the scenario
counts, the optimizer, early stopping and the baselines. The shipped problems
(``wmrjax/examples/*.toml``): ``section_6_1`` (default), ``car_schedule``, ``torque_2_1``.
Every option below overrides the file's value.

Writes ``gains.json`` (the tuned gains: ``[gains] file`` of any problem reads it),
``summary.json`` (with the whole resolved problem and every certified radius of the initial
and tuned gains), ``history.json``, ``checkpoint.json`` (a killed run resumes from it),
``loss.png``, ``schedule.png``, ``trajectories.png`` and, where the problem has a certificate,
``radii.png``.
"""

from __future__ import annotations

import argparse
import sys
from pathlib import Path

import jax

import wmrjax as w
from wmrjax import references as R
from wmrjax.cli import options
from wmrjax.examples import PROBLEMS, problem_file
from wmrjax.problem import Problem
from wmrjax.tune import certified, config, loop
from wmrjax.tune.job import baseline_budget, run
from wmrjax.tune.losses import LossWeights

_S = "(default: the file's)"


def parser():

    p = options.parser(__doc__.splitlines()[0], "results/tuning")
    _add_problem_options(p)
    _add_tuning_options(p)
    _add_plant_options(p)
    _add_loss_and_baseline_options(p)
    _add_requirement_and_run_options(p)
    return p


def _add_problem_options(p) -> None:
    """The problem file or shipped problem, the robot, the task, the reference and the initial errors."""

    S = _S
    p.add_argument(
        "file",
        type=options.problem_file,
        nargs="?",
        default=None,
        help="a problem file (TOML) with a [tune] section, or a shipped example",
    )
    options.add_set(p)
    p.add_argument(
        "--problem",
        default=None,
        choices=sorted(PROBLEMS),
        help="a shipped problem instead of a file (default: section_6_1_plant)",
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

    if a.file is not None and a.problem is not None:
        raise ValueError("give a problem file or --problem NAME, not both")
    path = a.file if a.file is not None else problem_file(a.problem or "section_6_1_plant")
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
    return options.with_set(problem.with_values(values) if values else problem, a)


def _law_values(a, problem, values) -> dict:
    """``--task`` and ``--robot`` as before problem files: the point task (and type (3,0)) take a
    static law, whose initial errors are physical (the output box's x and y kept)."""

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

    if text in R.FAMILIES:
        return {"reference": {"family": text}}
    path = Path(text)
    if path.suffix.lower() == ".csv" or path.is_file():
        return {"reference": {"family": "samples", "file": str(path.resolve())}}
    raise ValueError(f"--reference: expected a family ({', '.join(R.FAMILIES)}) or a CSV file of samples, got {text!r}")


def main(argv=None) -> int:

    p = parser()
    a = p.parse_args(argv)
    options.configure_xla()  # before JAX starts its backend

    jax.config.update("jax_enable_x64", True)  # float64 from the first check on (run() sets it too)
    try:
        problem = problem_from_args(a)
        setting = problem.setting("tuning")
        settings = config.read(problem.section("tune"), problem.section("certify"))
        family = settings.gain_spec(setting)
        loop.check(setting, family, settings.scenarios, settings.loss)
        if settings.requirement is not None:
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
