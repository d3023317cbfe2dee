"""The shipped example problems (problem files, TOML, with their sampled paths, CSV).

* ``section_6_1``: the paper's §6.1 robot ((2,0), e = 0, reference (62)), dynamic law at
  velocity level, poles at -1, with a ``[certify]`` section: the default of ``wmrjax certify``
  and ``wmrjax export``.
* ``section_6_1_plant``: the same robot on a real plant (20 Hz hold, saturation, noise,
  mismatch) with a ``[tune]`` section: the default of ``wmrjax tune``.
* ``s_path``: a (2,0) robot on an S-path sampled at 20 Hz (``s_path.csv``).
* ``car_waypoints``, ``steered_21``: a (1,1) car and a (2,1) robot on waypoint paths.
* ``car_schedule``: the (1,1) car with a 24-parameter gain schedule on random references.
* ``torque_2_1``: type (2,1) at torque level with outer and inner (Lemma 1) gains.
* ``section_6_1_position_grid``, ``random_references``, ``sampled_lane_change``: sweeps.

Every command takes a path or one of these names: ``wmrjax sweep s_path``.
"""

from __future__ import annotations

from pathlib import Path

__all__ = ["PROBLEMS", "problem_file"]

HERE = Path(__file__).resolve().parent
PROBLEMS = {p.stem: p for p in sorted(HERE.glob("*.toml"))}
"""Name -> path of every shipped example problem."""


def problem_file(name: str) -> Path:
    """The path of a shipped problem.

    Args:
      name: a key of :data:`PROBLEMS` (a file name without ``.toml``).

    Raises:
      ValueError: naming the choices, when ``name`` is not shipped.
    """
    if name not in PROBLEMS:
        raise ValueError(f"problem must be a file or one of {sorted(PROBLEMS)}, got {name!r}")
    return PROBLEMS[name]
