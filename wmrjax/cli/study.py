"""Multi-seed study on equal terms: the gradient tuner against the baselines users would pick,
held-out loss against compute (``wmrjax study``; the study itself: :mod:`wmrjax.tune.study`).

    wmrjax study --out results/tuning_study
    wmrjax study --problems section_6_1_plant wmrjax/examples/s_path.toml --seeds 10 --out DIR
    wmrjax study --problems s_path --seeds 2 --set tune.steps=10 --out DIR   # every problem smaller
"""

from __future__ import annotations

import jax
import numpy as np

from wmrjax.certify import Slice
from wmrjax.cli import machine, options, problem_args, running
from wmrjax.problem import Problem
from wmrjax.tune.study import DEFAULT_PROBLEMS, METHODS, problem_path, study


def parser():
    """The argument parser of ``wmrjax study``."""
    p = options.parser(__doc__.splitlines()[0], "results/tuning_study")
    p.add_argument(
        "--problems",
        nargs="+",
        default=list(DEFAULT_PROBLEMS),
        help="shipped problem names (wmrjax/examples) or problem files (TOML with [tune])",
    )
    p.add_argument("--seeds", type=options.count, default=10, help="seeds per problem (scenario sets, streams)")
    p.add_argument("--methods", nargs="+", default=list(METHODS), choices=METHODS, help="methods to run")
    p.add_argument("--points", type=options.count, default=8, help="log-spaced compute points up to the budget")
    p.add_argument(
        "--budget",
        type=options.positive,
        default=1.0,
        help="every baseline's budget as a multiple of the gradient run's forward-rollout equivalents",
    )
    p.add_argument(
        "--set",
        dest="set_values",
        type=problem_args.key_value,
        action="append",
        default=[],
        metavar="KEY=VALUE",
        help="one value of every problem by its dotted key, a TOML value (tune.steps=10, tune.scenarios.train=16)",
    )
    p.add_argument(
        "--require-radius",
        default=None,
        metavar="R",
        help="a certified-region requirement for every problem that can keep one (a radius, 'initial' "
        "or 'box'; see wmrjax tune --help); the others run without and say so",
    )
    p.add_argument(
        "--require-slice", default=str(Slice.FULL), choices=[str(s) for s in Slice], help="the requirement's slice"
    )
    return p


def problems_of(args) -> dict:
    """The problems of the command line's options, overrides applied: name -> (problem, requirement).

    Raises:
      ValueError: an unknown problem or unreadable file, two problems of one name, a bad override.
    """
    jax.config.update("jax_enable_x64", True)  # the tuner runs in float64

    require = None if args.require_radius is None else (_radius(args.require_radius), args.require_slice)
    problems = {}
    for spec in args.problems:
        name, path = problem_path(spec)
        if name in problems:
            raise ValueError(f"--problems: two problems named {name!r}")
        over = dict(args.set_values)
        problem = Problem.load(path)
        problems[name] = (problem.with_values(over) if over else problem, require)
    return problems


def _radius(text: str):
    """``--require-radius``: 'initial', 'box' or a radius >= 0."""
    if text in ("initial", "box"):
        return text
    v = float(text)
    if not v >= 0 or not np.isfinite(v):
        raise ValueError(f"--require-radius: expected a radius >= 0, 'initial' or 'box', got {text!r}")
    return v


def main(argv=None) -> int:
    """Run ``wmrjax study`` with ``argv`` (default: the process's arguments); return the exit status."""
    p = parser()
    a = p.parse_args(argv)
    machine.configure_xla()  # before JAX starts its backend
    try:  # the problems named by the options: a bad one is a bad option
        problems = problems_of(a)
    except ValueError as e:
        options.fail(p, str(e))
    r = running.work(
        p,
        a,
        lambda progress: study(
            problems, a.out, seeds=a.seeds, methods=a.methods, points=a.points, budget=a.budget, log=progress
        ),
    )
    print(f"wrote {a.out}/study.csv, summary.json, study.png ({r.wall_time_s:.0f} s)")
    return 0
