r"""Identify the robot from its logs: the plant's geometry and input scales, with 95 % intervals.

    python -m experiments.identify experiments/problems/car_11.toml --log run1.csv --log run2.csv \
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
import time
import tomllib
from pathlib import Path

import numpy as np

from experiments import common
from wmrjax import identify as I
from wmrjax import io
from wmrjax.problem import Problem
from wmrjax_cli import files, options


def run(out: Path, problem: Problem, logs, *, holdout=(), period=None, segment=2.0, max_delay=0, progress=None) -> dict:
    """Identify the plant of ``problem`` (loaded from its file) from ``logs`` (paths); write into ``out``."""
    say = progress or (lambda msg: print(msg, flush=True))
    common.enable_x64()
    t0 = time.time()
    model = I.sections.plant_model(problem.setting("identify"), period)
    fit_logs, held = ([read_log(p, model.robot) for p in paths] for paths in (logs, holdout))
    options = I.FitOptions(segment=segment, max_delay=max_delay)
    say(
        f"identify a {model.robot.name} robot ({model.level}) from {len(fit_logs)} log(s), {sum(len(x.t) for x in fit_logs)} samples"
    )
    ident = I.identify(model, fit_logs, options)
    summary = {
        "experiment": "identify",
        "problem_name": problem.title,
        "problem": problem.resolved(),
        **ident.summary(),
    }
    if held:
        say(f"predict {len(held)} held-out log(s)")
        summary["holdout"] = _holdout(ident, held)
    plant = summary["problem"].get("plant", {})
    section = I.sections.plant_section(ident, plant, ", ".join(Path(p).name for p in logs))
    files.write_bytes(out / "plant.toml", section.encode())
    written = ["summary.json", "plant.toml", "paths.png"]
    text = I.sections.with_plant_section(io.read_small_text(problem.source, "problem file"), section)
    try:  # the problem with the identified plant, if it loads from --out (relative paths may not)
        Problem.from_dict(tomllib.loads(text), base=out.resolve())
        files.write_bytes(out / "problem.toml", text.encode())
        written.append("problem.toml")
    except ValueError as err:
        summary["problem_toml_not_written"] = f"{err}; put plant.toml's section into the problem file instead"
    _figure(ident, out / "paths.png")
    summary["files"] = written
    summary["wall_time_s"] = time.time() - t0
    common.write_json(out / "summary.json", summary)
    return summary


def read_log(path: Path, robot):
    """A CSV log, or a Parquet one (by its ``.parquet`` suffix)."""
    path = Path(path)
    if path.suffix != ".parquet":
        return I.read_log(path, robot)
    data, header = files.read_parquet_columns(path, I.columns(robot), f"log of a {robot.name} robot")
    return I.log_from_columns(path.name, data, header, robot)


def _holdout(ident, logs) -> dict:
    fitted = I.prediction_error(ident, logs)
    nominal = I.prediction_error(ident, logs, theta=np.ones(len(ident.model.names)))
    ch = ident.model.channels
    return {
        log.name: {"identified_rms": dict(zip(ch, map(float, a))), "nominal_rms": dict(zip(ch, map(float, b)))}
        for log, a, b in zip(logs, fitted, nominal)
    }


def _figure(ident, path: Path) -> None:
    plt = files.headless_pyplot()
    n = len(ident.log_names)
    fig, axes = plt.subplots(1, n, figsize=(5 * n, 4.5), squeeze=False)
    seg = ident.segments
    for j, ax in enumerate(axes[0]):
        rows = np.flatnonzero(seg.log == j)
        for k, g in enumerate(rows):
            m = seg.mask[g] > 0
            ax.plot(*seg.measured[g, m, :2].T, ".", ms=2, color="0.6", label="logged" if k == 0 else None)
            ax.plot(
                *ident.predicted[g, m, :2].T, "-", lw=1, color="C0", label="fitted (per segment)" if k == 0 else None
            )
        ax.set(xlabel="x [m]", ylabel="y [m]", title=f"{ident.log_names[j]}: logged and fitted paths", aspect="equal")
        ax.legend(loc="best", fontsize=8)
    files.write_png(fig, path)
    plt.close(fig)


def _parser():
    p = common.parser(__doc__.splitlines()[0], "results/identify")
    p.add_argument(
        "file", type=Path, help="the problem file of the robot (TOML): its type, level, geometry and [plant]"
    )
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
    p = _parser()
    a = p.parse_args(argv)
    options.configure_xla()  # before JAX starts its backend
    try:
        common.enable_x64()
        problem = Problem.load(a.file)  # loaded once: a sampled path's spline is built at load
        model = I.sections.plant_model(problem.setting("identify"), a.period)
        for path in a.log + a.holdout:  # every log checked before anything compiles
            I.check_log(read_log(path, model.robot), model.period, model.input_limit)
    except ValueError as e:
        p.error(str(e))
    s = options.work(
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
    for name, e in s["parameters"].items():
        if e["identifiable"]:
            lo, hi = e["interval_95"]
            print(f"{name:16s} {e['estimate']:.6g} +- {e['std_error']:.2g}   95 %: [{lo:.6g}, {hi:.6g}]")
        else:
            print(f"{name:16s} not identifiable: {e['note']}")
    print(f"wrote {a.out}")
    return 0


if __name__ == "__main__":
    sys.exit(main())
