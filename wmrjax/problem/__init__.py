r"""A user's problem: controller, geometry, reference, plant, gains, initial conditions, horizon.

One description serves every job: a sweep runs it over many starts, the tuner improves its
gains, the certification says from where it is safe. Build it in Python
(:meth:`Problem.from_dict`) or read it from its file form (:meth:`Problem.load`, TOML)::

    title = "my robot on my path"
    [controller]
    law = "dynamic"                      # or "static"
    robot = "(2,0)"                      # a list: one setting per type
    level = "velocity"                   # or "torque"; a list: one setting per level
    [geometry]
    e = 0.15                             # [m]; L [m], delta [rad]
    [plant]                              # optional: the robot the law does not know exactly
    input_limit = [1.5, 2.0]             # |u_i| <= limit_i [m/s, rad/s; per s at torque level]
    input_scale = 1.0                    # true input = scale * command ([[s1, s2]]: one per input)
    geometry_scale = 1.0                 # the plant's L and e = scale * the law's
    control_period = 0.05                # [s]: a digital controller (zero-order hold) ...
    noise_std = [0.01, 0.01, 0.005]      # ... measuring X with this noise [m, m, rad]
    noise_seed = 0
    [reference]
    family = "samples"                   # every family of wmrjax.references.FAMILIES
    file = "path.csv"                    # relative to this file (or t = [...], x = [...], y = [...])
    [initial]
    space = "output"                     # errors of the output jet; or "physical" (posture)
    x = { min = -1.0, max = 1.0, num = 11 }        # a grid; or random = { count, seed } with
    y = { min = -1.0, max = 1.0, num = 11 }        # { low, high } ranges; or points = [[...]]
    [gains]
    poles = 1.0                          # or omega, zeta (lam), or coefficients, or file
    [simulation]
    t_final = 10.0                       # [s]
    dt = 0.01                            # [s]
    [[case]]                             # optional: named variants, e.g. default and tuned gains
    name = "tuned"
    gains = { file = "tuned/gains.json" }

Every value of a swept quantity is a number (or a vector), a list of them (an axis), or a
table ``{ min, max, num }``; the initial conditions may also be random (``{ low, high }``
ranges with ``random = { count, seed }``) or an explicit list of error vectors (``points``).
A sweep runs the Cartesian product of the axes (and every case); the tuner and the
certification take one value of each, and read their own sections (``[tune]``,
``[certify]``). Everything is validated key by key, before anything compiles; errors are
:class:`ProblemError` (a ``ValueError``) naming the key and the expected form.

:func:`place` (:mod:`wmrjax.controllers.placement`) is the one placement of an initial state
near a reference, and :meth:`Setting.run` the one run of a problem: the tuner, the sweep and the
certification's rollouts go through :func:`wmrjax.simulate` with them.

The package, by concept: :mod:`~wmrjax.problem.schema` (the sections, :class:`ProblemError`,
the value readers), :mod:`~wmrjax.problem.file` (:class:`Problem`),
:mod:`~wmrjax.problem.setting` (:class:`Setting`, :class:`RunInputs`),
:mod:`~wmrjax.problem.sections`, :mod:`~wmrjax.problem.reference` and
:mod:`~wmrjax.problem.gains_file` (the sections' parsers, the tuned-gains file format).
"""

from __future__ import annotations

from wmrjax.controllers.law import Task
from wmrjax.controllers.placement import Space, initial_keys, place
from wmrjax.problem.file import Problem
from wmrjax.problem.gains_file import GAIN_FILE_KIND, GainsFile, gains_file_dict, gains_owner, read_gains_file
from wmrjax.problem.reference import random_options, reference_axis
from wmrjax.problem.schema import (
    CASE_NAME,
    CASE_NAME_MAX,
    JOB_SECTIONS,
    SECTIONS,
    Law,
    ProblemError,
    check_keys,
    choice,
    integer,
    nonnegative,
    positive,
)
from wmrjax.problem.sections import controller, initial_box, simulation
from wmrjax.problem.setting import RunInputs, Setting, columns_of, law_state, unravel

__all__ = [
    "CASE_NAME",
    "CASE_NAME_MAX",
    "GAIN_FILE_KIND",
    "JOB_SECTIONS",
    "SECTIONS",
    "GainsFile",
    "Law",
    "Problem",
    "ProblemError",
    "RunInputs",
    "Setting",
    "Space",
    "Task",
    "check_keys",
    "choice",
    "columns_of",
    "controller",
    "gains_file_dict",
    "gains_owner",
    "initial_box",
    "initial_keys",
    "integer",
    "law_state",
    "nonnegative",
    "place",
    "positive",
    "random_options",
    "read_gains_file",
    "reference_axis",
    "simulation",
    "unravel",
]
