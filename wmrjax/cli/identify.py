r"""Identify the robot from its logs: the plant's geometry and input scales, with 95 % intervals.

    wmrjax identify wmrjax/examples/car_11.toml --log run1.csv --log run2.csv \
        --holdout run3.csv --out results/car/identify

Fits the problem's robot type, driven open loop by each log's commands, to the logged postures
by maximum likelihood (:func:`wmrjax.identify.identify`; the log format: docs/identify) and
writes into ``--out``: ``summary.json`` (the ``parameters`` block: per parameter ``estimate``,
``std_error``, ``interval_95``, ``identifiable``; the noise; residuals; the held-out logs'
prediction error, identified against nominal), ``plant.toml`` (the identified ``[plant]``
section: 95 % intervals as listed ranges), ``problem.toml`` (the problem with that section, for
the other jobs) and ``paths.png`` (logged against fitted paths).
"""

from __future__ import annotations

import sys
from pathlib import Path

from wmrjax import identify as I
from wmrjax.cli import machine, options, problem_args, running
from wmrjax.identify.job import read_log, run


def _parser():
    p = options.parser(__doc__.splitlines()[0], "results/identify")
    problem_args.add_problem_options(p, needs="of the robot: its type, level, geometry and [plant]")
    p.add_argument("--log", type=Path, action="append", required=True, help="a log to fit (CSV or Parquet; repeat)")
    p.add_argument("--holdout", type=Path, action="append", default=[], help="a log held out of the fit, predicted")
    p.add_argument(
        "--period",
        type=options.positive,
        default=None,
        help="the logs' sample period [s] (default: the problem's control_period)",
    )
    p.add_argument(
        "--segment",
        type=options.positive,
        default=2.0,
        help="segment length [s]: each segment's initial state is fitted",
    )
    p.add_argument(
        "--max-delay", type=options.nonnegative_int, default=0, help="the largest input delay tried [samples]"
    )
    return p


def main(argv=None) -> int:
    """Run ``wmrjax identify`` with ``argv`` (default: the process's arguments); return the exit status."""
    p = _parser()
    a = p.parse_args(argv)
    machine.configure_xla()  # before JAX starts its backend
    try:
        machine.enable_x64()
        problem = problem_args.problem_from_args(a)  # loaded once: a sampled path's spline is built at load
        model = I.sections.plant_model(problem.setting("identify"), a.period)
        for path in a.log + a.holdout:  # every log checked before anything compiles
            I.check_log(read_log(path, model.robot), model.period, model.input_limit)
    except ValueError as e:
        p.error(str(e))
    r = running.work(
        p,
        a,
        lambda progress: run(
            a.out,
            problem,
            a.log,
            holdout=a.holdout,
            period=a.period,
            segment=a.segment,
            max_delay=a.max_delay,
            progress=progress,
        ),
    )
    for e in r.identification.parameters:
        if e.identifiable:
            lo, hi = e.interval_95
            print(f"{e.name:16s} {e.estimate:.6g} +- {e.std_error:.2g}   95 %: [{lo:.6g}, {hi:.6g}]")
        else:
            print(f"{e.name:16s} not identifiable: {e.note}")
    print(f"wrote {a.out}")
    return 0


if __name__ == "__main__":
    sys.exit(main())
