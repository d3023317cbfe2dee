"""The shipped tuning problems: problem files (TOML) with a ``[tune]`` section.

* ``section_6_1`` (default): the §6.1 robot ((2,0), e = 0, reference (62)), dynamic law at
  velocity level, (omega, zeta) shared by both outputs: 2 parameters.
* ``car_schedule``: the (1,1) car with a 24-parameter gain schedule on random references.
* ``torque_2_1``: type (2,1) at torque level with outer and inner (Lemma 1) gains.

``python -m tuning --problem NAME`` runs one; ``python -m tuning FILE`` runs any problem file.
"""

from __future__ import annotations

from pathlib import Path

HERE = Path(__file__).resolve().parent
PROBLEMS = {p.stem: p for p in sorted(HERE.glob("*.toml"))}
"""Name -> path of every shipped tuning problem."""


def problem_file(name: str) -> Path:
    """The path of a shipped problem (ValueError naming the choices otherwise)."""
    if name not in PROBLEMS:
        raise ValueError(f"problem must be one of {sorted(PROBLEMS)}, got {name!r}")
    return PROBLEMS[name]
