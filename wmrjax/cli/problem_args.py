"""The problem a job reads, from its command line: one set of options with one meaning in every
job (:func:`add_problem_options`, :func:`problem_from_args`).

The positional ``PROBLEM`` is a problem file or the name of a shipped example
(:mod:`wmrjax.examples`). A few options name the values a user changes most (the robot, the
reference, the horizon, the gains); ``--set KEY=VALUE`` changes any value by its dotted key, a
TOML value, after them. Everything is validated where the problem file is, when the job reads
its setting, before anything compiles.
"""

from __future__ import annotations

import argparse
import os
import re
import tomllib
from pathlib import Path

import wmrjax as w
from wmrjax import examples
from wmrjax import references as R
from wmrjax.cli import options
from wmrjax.controllers import TABLE4
from wmrjax.problem import Problem

__all__ = ["add_problem_options", "key_value", "problem_file", "problem_from_args"]


def problem_file(text: str) -> Path:
    """A problem file, or the name of a shipped example (:mod:`wmrjax.examples`: ``s_path``)."""
    path = Path(text)
    if path.suffix or os.sep in text or path.exists():
        return path
    try:
        return examples.problem_file(text)
    except ValueError as exc:
        raise argparse.ArgumentTypeError(str(exc)) from None


_DOTTED_KEY = re.compile(r"[A-Za-z_][A-Za-z0-9_]*(\.[A-Za-z_][A-Za-z0-9_]*)*")


def key_value(text: str) -> tuple:
    """``KEY=VALUE``: a dotted key of the problem file and a TOML value (``0.02``, ``[5.5, 1.0]``,
    ``{low = -0.5, high = 0.5}``); a value that is not TOML is a string (``controller.robot=(1,1)``)."""
    key, sep, value = text.partition("=")
    key = key.strip()
    if not sep or not _DOTTED_KEY.fullmatch(key):
        raise argparse.ArgumentTypeError(
            f"expected KEY=VALUE with a dotted key (plant.control_period=0.02), got {text!r}"
        )
    try:
        return key, tomllib.loads(f"v = {value.strip()}")["v"]
    except tomllib.TOMLDecodeError:
        return key, value.strip()


def add_problem_options(p: argparse.ArgumentParser, *, default: str | None = None, needs: str = "") -> None:
    """The positional ``PROBLEM``, ``--set`` and the named problem options.

    Args:
      p: the job's parser.
      default: the shipped example a job runs without ``PROBLEM`` (None: ``PROBLEM`` is required).
      needs: what the job needs of the file, for the help (``"with a [tune] section"``).
    """
    p.add_argument(
        "file",
        metavar="PROBLEM",
        type=problem_file,
        nargs="?" if default else None,
        default=examples.problem_file(default) if default else None,
        help=f"a problem file (TOML) {needs}, or the name of a shipped example".replace("  ", " "),
    )
    g = p.add_argument_group("the problem", "each option sets values of the problem file; --set sets any, after them")
    g.add_argument(
        "--set",
        dest="set_values",
        type=key_value,
        action="append",
        default=[],
        metavar="KEY=VALUE",
        help="one value by its dotted key, a TOML value (plant.control_period=0.02, plant.input_limit=[5.5,1.0], "
        "tune.steps=10, certify.eps=0.02); repeat for several",
    )
    g.add_argument(
        "--robot",
        default=None,
        help="robot type (3,0), (2,0), (2,1), (1,1) or (1,2), with its default geometry (the paper's on a paper "
        "reference) and heading offset unless --geometry or --heading-offset",
    )
    g.add_argument("--task", default=None, choices=[str(t) for t in w.Task], help="posture: dynamic law; point: static")
    g.add_argument("--level", default=None, choices=[str(lv) for lv in w.Level], help="velocity or torque level")
    g.add_argument(
        "--reference", default=None, help=f"a reference family ({', '.join(R.FAMILIES)}) or a CSV file t,x,y"
    )
    g.add_argument("--heading-offset", type=options.finite, default=None, help="reference heading offset [rad]")
    g.add_argument(
        "--geometry", type=options.finite, nargs=3, default=None, metavar=("L", "E", "DELTA"), help="[m, m, rad]"
    )
    g.add_argument("--t-final", type=options.positive, default=None, help="horizon [s]")
    g.add_argument("--dt", type=options.positive, default=None, help="RK4 step [s]")
    g.add_argument("--control-dt", type=options.positive, default=None, help="controller period (zero-order hold) [s]")
    g.add_argument("--poles", type=options.positive, default=None, help="closed-loop poles at -POLES [1/s]")
    g.add_argument("--gains", type=Path, default=None, help="a gains file (gains.json of wmrjax tune)")


_KEYS = {
    "level": "controller.level",
    "heading_offset": "reference.heading_offset",
    "t_final": "simulation.t_final",
    "dt": "simulation.dt",
    "control_dt": "plant.control_period",
}
"""Option -> the dotted key it sets."""


def problem_from_args(a: argparse.Namespace) -> Problem:
    """The problem of ``a.file`` with the problem options, then ``--set``, applied.

    Raises:
      ValueError: a bad combination or value (``--poles`` with ``--gains``, an unknown reference).
    """
    problem = Problem.load(a.file)
    values = {key: getattr(a, k) for k, key in _KEYS.items() if getattr(a, k) is not None}
    if a.poles is not None and a.gains is not None:
        raise ValueError("give --poles or --gains, not both")
    if a.poles is not None:
        values["gains"] = {"poles": a.poles}
    if a.gains is not None:
        values["gains"] = {"file": str(a.gains.resolve())}
    if a.reference is not None:
        values["reference"] = _reference(a.reference)
    values |= _law(a, problem)
    if a.geometry is not None:
        values["geometry"] = dict(zip(("L", "e", "delta"), a.geometry))
    values |= dict(a.set_values)
    return problem.with_values(values) if values else problem


def _reference(text: str) -> dict:
    """``--reference``: a family name, or a CSV file of samples (t, x, y)."""
    if text in R.FAMILIES:
        return {"family": text}
    path = Path(text)
    if path.suffix.lower() == ".csv" or path.is_file():
        return {"family": "samples", "file": str(path.resolve())}
    raise ValueError(f"--reference: expected a family ({', '.join(R.FAMILIES)}) or a CSV file of samples, got {text!r}")


def _law(a, problem: Problem) -> dict:
    """``--robot`` and ``--task``: the law the task needs (a point or type (3,0): a static law, whose
    initial errors are physical), and with ``--robot`` the type's geometry and heading offset."""
    if a.robot is None and a.task is None:
        return {}
    ctrl = problem.data["controller"]
    robot = w.robot_type(a.robot or ctrl["robot"]).name
    task = w.Task(a.task or ctrl.get("task", w.Task.POSTURE))
    law = "static" if task == w.Task.POINT or robot not in TABLE4 else "dynamic"  # (3,0): Prop 3
    out = {"controller.robot": robot, "controller.law": law, "controller.task": str(task)}
    ini = problem.data["initial"]
    if law == "static" and ini.get("space", "output") == "output":
        out["initial"] = {"space": "physical", **{k: v for k, v in ini.items() if k in ("random", "x", "y")}}
    row = TABLE4.get(robot)
    if a.robot is not None and a.geometry is None and row is not None:
        family = _reference(a.reference)["family"] if a.reference else problem.data["reference"].get("family")
        paper = family in R.FAMILIES and R.FAMILIES[family].paper and row.paper_geometry is not None
        g = row.paper_geometry if paper else row.default_geometry
        out["geometry"] = {k: float(v) for k, v in g._asdict().items()}
    if a.robot is not None and a.heading_offset is None:
        out["reference.heading_offset"] = None
    return out
