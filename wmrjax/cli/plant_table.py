r"""The nominal certificate on the problem's own loop, feature by feature.

    wmrjax plant-table wmrjax/examples/s_path.toml --out results/s_path/plant_table

From the nominal exact map's worst initial error (position slice, or ``--slice full``) scaled
to 0.90, 0.95, 0.98 and 0.995 of the nominal proved radius, runs of: the nominal continuous
loop; the loop with each feature of the problem's ``[plant]`` alone (input limits, the
controller period with its zero-order hold, the input or geometry scales, the noise); limits
and period together; and the whole ``[plant]``. Each cell is the run's smallest distance to the
singular set (:func:`wmrjax.certify.real_loop_distances`: at every step, at every sample of a
digital controller; a listed scale: the smallest over its values; noise: realisation 0), and
``failed`` where the run failed. A cell below eps inside the nominal ball is the nominal
certificate failing on that loop (issue 54). Writes ``summary.json`` and prints the table.
"""

from __future__ import annotations

import sys
from pathlib import Path

import numpy as np

from wmrjax import _files as files
from wmrjax import certify as C
from wmrjax.cli import machine, options, problem_args, running
from wmrjax.tune.certified import DEFAULT_EPS

FACTORS = (0.90, 0.95, 0.98, 0.995)


def loops(plant: dict) -> list:
    """``(label, [plant] section or None)``: nominal, each feature alone, limits with the period,
    and the whole section (the combinations the section has, each once)."""
    single = [
        (k, {k: plant[k]}) for k in ("input_limit", "control_period", "input_scale", "geometry_scale") if k in plant
    ]
    out = [("nominal", None)] + single
    if "input_limit" in plant and "control_period" in plant:
        out.append(("input_limit + control_period", {k: plant[k] for k in ("input_limit", "control_period")}))
    if not any(section == plant for _, section in out):
        out.append(("whole [plant]", plant))
    return out


def run(out: Path, problem, basis: str = C.Slice.POSITION, progress=print) -> dict:
    """The table of ``problem`` (a :class:`wmrjax.problem.Problem` with a ``[plant]``)."""
    machine.enable_x64()
    plant = problem.data.get("plant")
    if not plant:
        raise ValueError("the problem has no [plant] section: its loop is the nominal one")
    base = problem.with_values({"plant": None}).setting("certification")
    eps = float(problem.section("certify").get("eps", DEFAULT_EPS))
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
        progress(f"{label}: " + ", ".join(_cell(v, eps) for v in d))
    summary = {
        "experiment": "plant_table",
        "problem_name": problem.title,
        "problem": problem.resolved(),
        "slice": basis,
        "eps": eps,
        "nominal_radius": em.lower_bound,
        "nominal_radius_kind": "proved",
        "worst_error_direction": [float(v) for v in worst / np.linalg.norm(worst)],
        "factors": list(FACTORS),
        "rows": rows,
    }
    out.mkdir(parents=True, exist_ok=True)
    files.write_json(out / "summary.json", summary)
    return summary


def _cell(d: float, eps: float) -> str:
    return "**failed**" if d == 0 else (f"**{d:.3f} < eps**" if d < eps else f"{d:.3f}")


def table(summary: dict) -> str:
    """The summary as a Markdown table."""
    head = "| loop | " + " | ".join(f"{f}x" for f in summary["factors"]) + " |"
    lines = [head, "|---" * (len(summary["factors"]) + 1) + "|"]
    for r in summary["rows"]:
        lines.append(f"| {r['loop']} | " + " | ".join(_cell(d, summary["eps"]) for d in r["min_distance"]) + " |")
    return "\n".join(lines)


def main(argv=None) -> int:
    """Run ``wmrjax plant-table`` with ``argv`` (default: the process's arguments); return the exit status."""
    p = options.parser(__doc__.splitlines()[0], "results/plant_table")
    problem_args.add_problem_options(p, needs="with a [plant] section")
    p.add_argument(
        "--slice", default=str(C.Slice.POSITION), choices=[str(s) for s in C.Slice], help="the slice of initial errors"
    )
    a = p.parse_args(argv)
    machine.configure_xla()  # before JAX starts its backend (the runs are vmapped on one device)
    try:
        machine.enable_x64()
        problem = problem_args.problem_from_args(a)
    except ValueError as e:
        p.error(str(e))
    s = running.work(p, a, lambda progress: run(a.out, problem, a.slice, progress=progress))
    print(f"nominal {s['slice']}-slice radius {s['nominal_radius']:.4f} (proved), eps = {s['eps']}:")
    print(table(s))
    return 0


if __name__ == "__main__":
    sys.exit(main())
