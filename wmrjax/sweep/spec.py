"""The sweep of a problem file: :class:`wmrjax.problem.Problem` (the file form, validated key by
key before anything compiles) turned into a :class:`Plan` -- groups of runs, one per case,
robot type and level, each the Cartesian product of five axes: geometry, plant, reference,
gains, initial condition -- cut into blocks.

The file format is the problem's (see :mod:`wmrjax.problem` and docs/problem_files.md); the sweep reads
its ``[simulation]`` keys ``block``, ``error_tol``, ``distance_every`` and its ``[classify]``
section. ``wmrjax/examples/*.toml`` are complete examples.
"""

from __future__ import annotations

import dataclasses
import hashlib
import json
from pathlib import Path

import numpy as np

from wmrjax.problem import (  # noqa: F401  (the file form's helpers, as the sweep's modules use them)
    Law,
    Problem,
    ProblemError,
    Setting,
    Space,
    Task,
    check_keys,
    columns_of,
    initial_keys,
    integer,
    positive,
    unravel,
)
from wmrjax.problem import controller as make

SpecError = ProblemError  # a sweep file that cannot run (the name the sweep's callers know)
Group = Setting  # one group of runs: one case, robot type and level


@dataclasses.dataclass
class Plan:
    """A validated sweep."""

    problem: Problem
    spec: dict
    source: Path
    law: Law
    task: Task
    space: Space
    groups: list
    t_final: float
    dt: float
    n_steps: int
    block: int  # runs per compiled block (per device)
    save_every: int  # steps between the samples min_distance is taken on
    error_tol: float | None
    position_tol: float
    heading_tol: float
    swept: list  # the columns with more than one value (map axes)
    fingerprint: str

    @property
    def plant(self) -> bool:
        """Some group closes the law around a plant (limits, mismatch, sampling)."""
        return any(g.plant for g in self.groups)

    @property
    def n_runs(self) -> int:
        """The number of runs of all groups together."""
        return sum(g.size for g in self.groups)

    def blocks(self):
        """``(group index, first run in group, runs)`` for every block, in table order."""
        out = []
        for gi, g in enumerate(self.groups):
            for start in range(0, g.size, self.block):
                out.append((gi, start, min(self.block, g.size - start)))
        return out


def load(path) -> Plan:
    """Read, validate and plan a sweep file; every error is a :class:`SpecError` (a ValueError)
    naming the key, raised before JAX compiles anything."""
    return plan(Problem.load(path))


def plan(problem: Problem) -> Plan:
    """Plan the sweep of a problem (see :func:`load`)."""
    groups = problem.settings()
    first = groups[0]
    for g in groups[1:]:
        if (g.law, g.task, g.space) != (first.law, first.task, first.space):
            raise SpecError(
                "[[case]]: the cases of one sweep share the law, the task and the initial space "
                f"(got {first.law}/{first.task}/{first.space} and {g.law}/{g.task}/{g.space})"
            )
        if (g.t_final, g.dt) != (first.t_final, first.dt):
            raise SpecError("[[case]]: the cases of one sweep share the horizon and the step")
    sim = problem.data["simulation"]
    n_steps = first.n_steps
    # a block never exceeds the largest group: a block of 1e7 for 9 runs padded every call to 1e7 runs
    block = min(integer("simulation", "block", sim.get("block", 256), 1), max(g.size for g in groups))
    every = sim.get("distance_every", max(1, int(round(0.1 / first.dt))))
    every = min(integer("simulation", "distance_every", every, 1), n_steps)
    tol = sim.get("error_tol", 1e-3)
    if tol == "none":
        tol = None
    elif not (isinstance(tol, (int, float)) and not isinstance(tol, bool) and np.isfinite(tol) and tol > 0):
        raise SpecError(f'[simulation] error_tol: expected a number > 0 or "none", got {tol!r}')
    position_tol, heading_tol = read_section(problem.data)
    swept = []  # columns with more than one value within a group (defaults differ across groups)
    for g in groups:
        for a in g.axes:
            for k, v in a.columns.items():
                if k not in swept and len(set(np.asarray(v).tolist())) > 1:
                    swept.append(k)
    labels = [
        k
        for k, f in (
            ("case", lambda g: g.case),
            ("robot", lambda g: g.ctrl.robot.name),
            ("level", lambda g: str(g.ctrl.level)),
        )
        if len({f(g) for g in groups}) > 1
    ]
    swept = labels + swept
    fp = hashlib.sha256(json.dumps(problem.resolved(), sort_keys=True, default=str).encode())
    return Plan(
        problem,
        problem.data,
        problem.source,
        first.law,
        first.task,
        first.space,
        groups,
        first.t_final,
        first.dt,
        n_steps,
        block,
        every,
        tol,
        position_tol,
        heading_tol,
        swept,
        fp.hexdigest()[:16],
    )


def controller(law, kind: str, level, task):
    """The controller of a group (:func:`wmrjax.problem.controller`)."""
    return make(law, kind, level, task)


def read_section(data: dict) -> tuple[float, float]:
    """``(position_tol, heading_tol)`` of a problem's ``[classify]`` section ([m], [rad]; 0.01
    each by default): the schema :data:`wmrjax.problem.JOB_SECTIONS` validates at load."""
    cls = data.get("classify", {})
    check_keys("classify", cls, ("position_tol", "heading_tol"))
    return (
        positive("classify", "position_tol", cls.get("position_tol", 0.01)),
        positive("classify", "heading_tol", cls.get("heading_tol", 0.01)),
    )
