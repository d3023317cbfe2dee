r"""Tracking against the certified region: a Pareto front from tuned, certified points
(``wmrjax pareto``; the front itself: :mod:`wmrjax.tune.pareto`).

    wmrjax pareto wmrjax/examples/s_path.toml --out results/s_path/pareto \
        --slice position --fractions 0 0.25 0.5 0.75 1 1.25
"""

from __future__ import annotations

import jax

from wmrjax.certify import Slice
from wmrjax.cli import machine, options, problem_args, running
from wmrjax.tune import certified, config
from wmrjax.tune.pareto import run


def parser():
    """The argument parser of ``wmrjax pareto``."""
    p = options.parser(__doc__.splitlines()[0], "results/pareto")
    problem_args.add_problem_options(p, needs="with a [tune] section")
    p.add_argument(
        "--slice",
        default=str(Slice.FULL),
        choices=[str(s) for s in Slice],
        help="the slice of initial errors whose exact-map radius is required (default: full)",
    )
    g = p.add_mutually_exclusive_group()
    g.add_argument(
        "--fractions",
        type=options.nonnegative,
        nargs="+",
        default=None,
        help="required radii as multiples of the initial gains' radius (default: 0 0.25 0.5 0.75 1 1.25)",
    )
    g.add_argument(
        "--radii", type=options.nonnegative, nargs="+", default=None, help="required radii [output-error units: m, m/s]"
    )
    return p


def main(argv=None) -> int:
    """Run ``wmrjax pareto`` with ``argv`` (default: the process's arguments); return the exit status."""
    p = parser()
    a = p.parse_args(argv)
    machine.configure_xla()  # before JAX starts its backend
    jax.config.update("jax_enable_x64", True)
    try:
        problem = problem_args.problem_from_args(a)
        setting = problem.setting("tuning")
        settings = config.read(problem.section("tune"), problem.section("certify"))
        certified.check(setting, settings.gain_family(setting))
    except ValueError as e:
        p.error(str(e))
    r = running.work(p, a, lambda progress: run(problem, a.out, a.slice, a.fractions, a.radii, log=progress))
    for pt in r.points:
        print(
            f"required {pt['required_radius']:.4g}: radius {pt['tuned_radius']:.4g} (falsified "
            f"{pt['falsified_radius']}), held-out {pt['heldout_loss']:.4g}, certified {pt['certified']}"
        )
    print(f"initial gains: radius {r.initial['radius']:.4g}, held-out {r.initial['heldout_loss']:.4g}")
    print(f"wrote {a.out}/pareto.csv, pareto.png, summary.json, points/ ({r.wall_time_s:.0f} s)")
    return 0
