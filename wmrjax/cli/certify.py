r"""Lemma 2 certification of a problem's closed loop: every radius, checked by rollouts.

    wmrjax certify                                    # the paper's section 6.1
    wmrjax certify PROBLEM.toml --out results/mine    # any problem file
    wmrjax certify --robot "(2,1)" --reference figure_eight --out results/certify_21

For the problem's dynamic linearizing law (its geometry, reference, gains -- poles, damping
factors, a tuned-gains file, a schedule -- and horizon) this computes: the certified radii of
Lemma 2 with K2 three ways (the paper's eq 64 when the gains are the paper's, the automatic
Lyapunov bound, the exact ||e^{At}||; ||Phi(t, 0)|| for a schedule); the exact-map radius (the
largest ball of initial errors that keeps zeta(t) eps away from the singular set, from
zeta_err(t) = e^{At} zeta_err(0)) for the full error and for the position slice; an
empirical check by batch simulation (violations of (53) and singular runs inside every
ball, and the empirical safe radius per direction of the position slice); and the
gradient falsifier's smallest failing radius, full and position slice. These are the nominal
continuous loop's (``radius_labels`` says what each covers and how it is known). A ``[plant]``
section (limits, a digital controller, mismatch, noise) describes another loop:
``problem_certificate`` gives, per slice, the radius a proof covers for it (none yet for any
plant feature: ``not_covered`` lists them) and that loop's falsified radius, from its own runs;
a nominal radius above it is printed as a warning.

The problem's ``[certify]`` section sets eps, the sample counts and the map (see
``wmrjax/examples/section_6_1.toml``, the default); every option below overrides it.
Writes ``summary.json`` (with the whole resolved problem) and ``slice_map.png``: min_t
dist(zeta(t), S) over a grid of initial position errors (velocities equal to the
reference's), with the eps contour and every certified circle.

For (1,2) the singular set is curved (sigma(zeta) = 0, see wmrjax.certify.m1_closed_form): M1
is a one-dimensional minimisation, and the exact-map radius comes from a branch and bound
with a proved lower bound (``radius_exact_map_lower_bound``, ``radius_exact_map_gap``).
Every certificate's ratio to the falsified radius is in ``tightness``; ``wall_time_s`` is the
whole run. What contradicts the theory (Lemma 2 violated inside a certified ball, a certified
radius above a falsified one, an exact-map radius more than 1 % from its falsifier's) is listed
in ``alarms`` and printed, and the command exits with status 1 after writing its files. The batch simulations are spread over one JAX host device per core (``--devices``).
"""

from __future__ import annotations

import os
import sys
from pathlib import Path

import wmrjax as w
from wmrjax import examples
from wmrjax import references as R
from wmrjax.certify.job import run, settings, setup
from wmrjax.cli import common, options
from wmrjax.problem import Problem

DEFAULT_PROBLEM = examples.problem_file("section_6_1")
EMPIRICAL_GRID = 48  # radii per ray of certify.empirical_radius (its n_grid)


# option -> dotted key of the problem file it sets
_KEYS = {
    "level": "controller.level",
    "t_final": "simulation.t_final",
    "dt": "simulation.dt",
    "eps": "certify.eps",
    "n_empirical": "certify.n_empirical",
    "n_directions": "certify.n_directions",
    "n_starts": "certify.n_starts",
    "map_grid": "certify.map_grid",
    "heading_offset": "reference.heading_offset",
}


def problem_from_args(a):
    """The problem file (default: section 6.1) with the options given on the command line applied.
    As before problem files: ``--robot`` or ``--reference`` without ``--geometry`` take the
    paper's geometry along (62) and (66) where the paper has one, else the type's default
    (its Table 4 row), and the type's default heading offset unless ``--heading-offset``."""

    problem = Problem.load(a.file if a.file is not None else DEFAULT_PROBLEM)
    values = {key: getattr(a, k) for k, key in _KEYS.items() if getattr(a, k) is not None}
    if a.poles is not None and a.gains is not None:
        raise ValueError("give --poles or --gains, not both")
    if a.poles is not None:
        values["gains"] = {"poles": a.poles}
    if a.gains is not None:
        values["gains"] = {"file": str(Path(a.gains).resolve())}
    if a.robot is not None:
        values["controller.robot"] = w.robot_type(a.robot).name
    if a.reference is not None:
        values["reference"] = {"family": a.reference}
    if a.robot is not None or a.reference is not None:
        robot = values.get("controller.robot", problem.data["controller"]["robot"])
        ref = values.get("reference", problem.data["reference"]).get("family")
        row = w.controllers.TABLE4.get(robot)
        if a.geometry is None and row is not None:
            paper = ref in R.FAMILIES and R.FAMILIES[ref].paper
            g = row.paper_geometry if paper and row.paper_geometry is not None else row.default_geometry
            values["geometry"] = {k: float(v) for k, v in g._asdict().items()}
        if a.heading_offset is None:
            values["reference.heading_offset"] = None
    if a.geometry is not None:
        values["geometry"] = dict(zip(("L", "e", "delta"), a.geometry))
    return options.with_set(problem.with_values(values) if values else problem, a)


def _parser():
    """The command's options."""

    p = common.parser(__doc__.splitlines()[0], "results/certify")
    p.add_argument(
        "file",
        type=options.problem_file,
        nargs="?",
        default=None,
        help="a problem file (TOML) or a shipped example (default: section_6_1)",
    )
    options.add_set(p)
    p.add_argument("--case", default=None, help="the [[case]] to certify, when the problem has several")
    p.add_argument("--robot", default=None, help="robot type: (2,0), (2,1), (1,1) or (1,2)")
    p.add_argument("--reference", default=None, choices=sorted(R.REFERENCES), help="a named reference")
    p.add_argument("--level", default=None, choices=["velocity", "torque"], help="velocity or torque level")
    p.add_argument(
        "--poles", type=options.positive, default=None, help="closed-loop poles at -POLES [1/s] (1: the paper's)"
    )
    p.add_argument(
        "--gains",
        type=Path,
        default=None,
        help="a tuned-gains file (gains.json of wmrjax tune): complex poles, schedules",
    )
    p.add_argument("--t-final", type=options.positive, default=None, help="horizon [s]")
    _check_options(p)
    return p


def _check_options(p) -> None:
    """Options of the checks, the heading offset, the geometry and the devices."""

    p.add_argument("--eps", type=options.positive, default=None, help="Lemma 2's margin eps [zeta units: m, m/s]")
    p.add_argument("--dt", type=options.positive, default=None, help="RK4 step of the empirical checks [s]")
    p.add_argument(
        "--n-empirical", type=options.count, default=None, help="sampled initial errors (every K2 checked on them)"
    )
    p.add_argument(
        "--n-directions", type=options.count, default=None, help="rays of the position-slice empirical radius"
    )
    p.add_argument(
        "--n-starts",
        type=options.nonnegative_int,
        default=None,
        help="falsifier gradient starts per radius (0: no falsifier)",
    )
    p.add_argument(
        "--heading-offset",
        type=options.finite,
        default=None,
        help="reference heading offset [rad] (crab angle; default: the file's, else the type's)",
    )
    p.add_argument("--map-grid", type=options.grid_size, default=None, help="slice map resolution (N x N runs)")
    p.add_argument(
        "--geometry",
        type=options.finite,
        nargs=3,
        default=None,
        metavar=("L", "E", "DELTA"),
        help="robot geometry [m, m, rad]",
    )
    p.add_argument(
        "--devices",
        type=options.count,
        default=os.cpu_count() or 1,
        help="JAX host devices the batch simulations are spread over (one per core; sets XLA_FLAGS "
        "before JAX starts its backend)",
    )


def _report(s: dict, out: Path) -> int:
    """Prints the radii with what they cover, the falsified ones, the problem's certificate and the
    alarms; the exit status (1 on an alarm)."""
    labels = s["radius_labels"]
    print("nominal continuous loop:")
    for k, lab in labels.items():
        v = s.get(k)
        r = v.get("radius") if isinstance(v, dict) else v
        if r is not None:
            print(f"  {k} {r:.4f} ({lab['kind']})")
    pc = s["problem_certificate"]
    if pc["loop"] != ["nominal"]:
        print(f"problem's loop ({', '.join(pc['loop'])}):")
        for b in ("full", "position"):
            c = pc[b]
            proved = "none proved" if c["radius"] is None else f"{c['radius']:.4f} ({c['kind']})"
            falsified = "none found" if c["falsified_radius"] is None else f"{c['falsified_radius']:.4f} (estimated)"
            print(
                f"  {b}: certified radius {proved} (not covered: {', '.join(c['not_covered'])}); falsified {falsified}"
            )
    print(f"wrote {out}/summary.json and slice_map.png in {s['wall_time_s']:.0f} s")
    for msg in s["plant_warnings"]:
        print(f"warning: {msg}", file=sys.stderr)
    for msg in s["alarms"]:  # a result that contradicts the theory is an error, not a certificate
        print(f"error: {msg}", file=sys.stderr)
    return 1 if s["alarms"] else 0


def main(argv=None) -> int:

    p = _parser()
    a = p.parse_args(argv)
    options.configure_xla(a.devices)  # before JAX starts its backend
    try:
        common.enable_x64()
        problem = problem_from_args(a)
        cfg = settings(problem)
        setting, _, _ = setup(problem, a.case)
    except ValueError as e:
        p.error(str(e))
    # the largest batch: the empirical checks, the slice map, or every ray's grid of radii at once
    # (checked here: a batch too large otherwise aborts the process in the allocator, late)
    batch = max(cfg["n_empirical"], cfg["map_grid"] ** 2, (cfg["n_directions"] + 1) * EMPIRICAL_GRID)
    options.check_horizon(p, t_final=setting.t_final, dt=setting.dt, batch=batch, saved_every=10)
    s = options.work(p, a, lambda progress: run(a.out, problem, a.case, progress=progress))
    return _report(s, a.out)


if __name__ == "__main__":
    sys.exit(main())
