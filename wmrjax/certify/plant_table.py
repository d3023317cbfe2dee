r"""The nominal certificate on the problem's own loop, feature by feature (``wmrjax plant-table``).

From the nominal exact map's worst initial error (position slice, or the full one) scaled to
0.90, 0.95, 0.98 and 0.995 of the nominal proved radius, runs of: the nominal continuous loop;
the loop with each feature of the problem's ``[plant]`` alone (input limits, the controller
period with its zero-order hold, the input or geometry scales, the noise); limits and period
together; and the whole ``[plant]``. Each cell is the run's smallest distance to the singular
set (:func:`wmrjax.certify.real_loop_distances`: at every step, at every sample of a digital
controller; a listed scale: the smallest over its values; noise: realisation 0), and ``failed``
(0) where the run failed. A cell below eps inside the nominal ball is the nominal certificate
failing on that loop (issue 54).
"""

from __future__ import annotations

import dataclasses

import numpy as np

from wmrjax import _files as files
from wmrjax import certify as C
from wmrjax.certify.job import settings
from wmrjax.problem import Problem
from wmrjax.report import JobReport

FACTORS = (0.90, 0.95, 0.98, 0.995)
"""The initial errors' fractions of the nominal proved radius."""


def loops(plant: dict) -> list:
    """``(label, [plant] section or None)``: nominal, each feature alone, limits with the period,
    and the whole section (the combinations the section has, each once).

    Args:
        plant: the problem's ``[plant]`` section (as written).
    """
    single = [
        (k, {k: plant[k]}) for k in ("input_limit", "control_period", "input_scale", "geometry_scale") if k in plant
    ]
    out = [("nominal", None)] + single
    if "input_limit" in plant and "control_period" in plant:
        out.append(("input_limit + control_period", {k: plant[k] for k in ("input_limit", "control_period")}))
    if not any(section == plant for _, section in out):
        out.append(("whole [plant]", plant))
    return out


@dataclasses.dataclass(frozen=True)
class PlantTableReport(JobReport):
    """The table (:func:`run`): per loop, the smallest distance to the singular set from each
    scaled worst error.

    Attributes:
        problem: the problem (with a ``[plant]``).
        slice: the slice of the nominal exact map (:class:`wmrjax.certify.Slice`).
        eps: the margin to the singular set [output-error units].
        nominal: the nominal loop's exact-map radius (proved; :class:`wmrjax.certify.ExactMapRadius`).
        worst_error: the initial error at the nominal proved radius, in the slice's output-error
            coordinates; the runs start from :data:`FACTORS` times it.
        rows: per loop, ``{"loop": label, "plant": section, "min_distance": [one per factor]}``
            (0: the run failed).
    """

    problem: Problem
    slice: C.Slice
    eps: float
    nominal: C.ExactMapRadius
    worst_error: np.ndarray
    rows: tuple

    def markdown(self) -> str:
        """The table in Markdown, a cell in bold where it fails or comes within eps."""
        head = "| loop | " + " | ".join(f"{f}x" for f in FACTORS) + " |"
        lines = [head, "|---" * (len(FACTORS) + 1) + "|"]
        for r in self.rows:
            lines.append(f"| {r['loop']} | " + " | ".join(cell(d, self.eps) for d in r["min_distance"]) + " |")
        return "\n".join(lines)

    def summary(self) -> dict:
        """``summary.json`` (plain JSON)."""
        w = np.asarray(self.worst_error)
        return files.jsonable(
            {
                "experiment": "plant_table",
                "problem_name": self.problem.title,
                "problem": self.problem.resolved(),
                "slice": self.slice,
                "eps": self.eps,
                "nominal_radius": self.nominal.lower_bound,
                "nominal_radius_kind": "proved",
                "worst_error_direction": [float(v) for v in w / np.linalg.norm(w)],
                "factors": list(FACTORS),
                "rows": list(self.rows),
            }
        )


def cell(d: float, eps: float) -> str:
    """One cell: the distance, in bold where the run failed or came within ``eps``."""
    return "**failed**" if d == 0 else (f"**{d:.3f} < eps**" if d < eps else f"{d:.3f}")


def run(out, problem, basis=C.Slice.POSITION, progress=print) -> PlantTableReport:
    """The table of ``problem``; writes ``summary.json`` into ``out``.

    Args:
        out: the output directory (``Path``; made if missing).
        problem: the problem (:class:`wmrjax.problem.Problem`) with a ``[plant]`` section.
        basis: the slice of initial errors (:class:`wmrjax.certify.Slice`).
        progress: called with each loop's row as it is measured.

    Returns:
        the :class:`PlantTableReport`.
    """
    plant = problem.data.get("plant")
    if not plant:
        raise ValueError("the problem has no [plant] section: its loop is the nominal one")
    base = problem.with_values({"plant": None}).setting("certification")
    eps = settings(problem)["eps"]
    params = base.params()
    em = C.exact_map_radius(base.ctrl, params, t_final=base.t_final, eps=eps, basis=basis)
    worst = np.asarray(em.worst_error) * (em.lower_bound / float(em.radius))
    errs = np.array([f * worst for f in FACTORS])
    rows = []
    for label, section in loops(plant):
        setting = problem.with_values({"plant": section}).setting("certification")
        n_plant = setting.axis("plant").size
        d = np.min([C.real_loop_distances(setting, params, errs, plant=i) for i in range(n_plant)], axis=0)
        rows.append({"loop": label, "plant": section, "min_distance": [float(v) for v in d]})
        progress(f"{label}: " + ", ".join(cell(v, eps) for v in d))
    report = PlantTableReport(problem, C.Slice(basis), eps, em, worst, tuple(rows))
    out.mkdir(parents=True, exist_ok=True)
    report.write_summary(out)
    return report
