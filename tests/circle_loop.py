"""The (2,0) test loop on the circle reference (e = 0: the distance to the singular set is
|chi1|), shared by the real-loop and held-reach tests."""

from wmrjax.problem import Problem


def circle_problem(plant=None, *, t_final: float, dt: float = 0.02, sections: dict | None = None) -> Problem:
    """The (2,0) law at e = 0 on the default circle (2 m, 1 m/s), poles -1, with ``plant`` (and
    further ``sections``, a job's table)."""
    data = {
        "controller": {"law": "dynamic", "robot": "(2,0)", "level": "velocity"},
        "geometry": {"e": 0.0},
        "reference": {"family": "circle"},
        "gains": {"poles": 1.0},
        "initial": {"space": "output", "x": 0.1},
        "simulation": {"t_final": t_final, "dt": dt},
    }
    if plant is not None:
        data["plant"] = plant
    data.update(sections or {})
    return Problem.from_dict(data)
