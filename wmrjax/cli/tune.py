r"""Tune the linearizing controller's gains by gradient descent through the simulator, against
random search and CMA-ES on the same terms.

    wmrjax tune PROBLEM.toml --out results/my_problem         # any problem file with [tune]
    wmrjax tune car_schedule --out results/car_schedule --set tune.steps=20

A problem file (:mod:`wmrjax.problem`) says the robot, the path, the plant and the initial
errors; its ``[tune]`` section (:mod:`wmrjax.tune.config`) the gain family, the loss, the scenario
counts, the optimizer, early stopping and the baselines. The shipped problems
with ``[tune]`` (:mod:`wmrjax.examples`): ``section_6_1_plant`` (default), ``car_schedule``,
``torque_2_1``. The problem options and ``--set`` change the file's values
(``--set tune.scenarios.train=16``, ``--set tune.requirement.radius=0.5``).

Writes ``gains.json`` (the tuned gains: ``[gains] file`` of any problem reads it),
``summary.json`` (with the whole resolved problem and every certified radius of the initial
and tuned gains), ``history.json``, ``checkpoint.json`` (a killed run resumes from it),
``loss.png``, ``schedule.png``, ``trajectories.png`` and, where the problem has a certificate,
``radii.png``.
"""

from __future__ import annotations

import sys

import jax

from wmrjax.certify import Slice
from wmrjax.cli import machine, options, problem_args, running
from wmrjax.tune import certified, config, loop
from wmrjax.tune.job import baseline_budget, run


def parser():
    """The job's options: the problem (:mod:`wmrjax.cli.problem_args`), the falsifier, a fresh start."""
    p = options.parser(__doc__.splitlines()[0], "results/tuning")
    problem_args.add_problem_options(p, default="section_6_1_plant", needs="with a [tune] section")
    p.add_argument(
        "--falsify",
        action="store_true",
        help="also falsify the initial and tuned gains' exact-map radii by rollouts (slower)",
    )
    return p


def main(argv=None) -> int:
    """Run ``wmrjax tune`` with ``argv`` (default: the process's arguments); return the exit status."""
    p = parser()
    a = p.parse_args(argv)
    machine.configure_xla()  # before JAX starts its backend

    jax.config.update("jax_enable_x64", True)  # float64 from the first check on (run() sets it too)
    try:
        problem = problem_args.problem_from_args(a)
        setting = problem.setting("tuning")
        settings = config.read(problem.section("tune"), problem.section("certify"))
        family = settings.gain_family(setting)
        loop.check(setting, family, settings.scenarios, settings.loss)
        if settings.requirement is not None:
            certified.check(setting, family, settings.requirement)
        baseline_budget(settings, family)
    except ValueError as e:
        p.error(str(e))
    r = running.work(
        p,
        a,
        lambda progress: run(problem, a.out, a.fresh, log=progress, falsify=a.falsify),
        hint=lambda msg: msg + "; or rerun with --fresh to start over" if "checkpoint" in msg else msg,
    )
    s, b = r.summary(), r.baselines
    print(
        f"{problem.title}: {s['n_parameters']} parameters; held-out loss initial {s['heldout_loss']['paper_gains']:.4g} "
        f"-> tuned {s['heldout_loss']['tuned']:.4g} (CMA-ES {b['cma_es']['best_heldout_loss']:.4g}, random search "
        f"{b['random_search']['best_heldout_loss']:.4g}); singular events {s['singularity_events']}; "
        f"gradient rollouts {s['rollouts']}, to match CMA-ES {s['rollouts_to_match']['cma_es']} (CMA-ES best after "
        f"{b['cma_es']['rollouts_to_best']:.0f}); {r.wall_time_s:.1f} s"
    )
    for line in radius_change_lines(r.radii):
        print(line)
    print(
        f"wrote {a.out}/gains.json, summary.json, history.json, checkpoint.json, loss.png, schedule.png, "
        "trajectories.png" + (", radii.png" if "initial" in r.radii else "")
    )
    return 0


def radius_change_lines(radii: dict) -> list:
    """The certified radii of the initial and the tuned gains on the console, per slice, with the
    change in percent (a tuned loop can track better and be certified from a smaller region:
    that was only in summary.json and radii.png)."""
    if "initial" not in radii:
        return [f"certified radii: {radii.get('skipped', 'none')}"]
    lines = []
    for key, block in radii["initial"].items():
        if not key.startswith("exact_map_") or key not in radii["tuned"]:
            continue
        r0 = block.get("lower_bound", block["radius"])
        r1 = radii["tuned"][key].get("lower_bound", radii["tuned"][key]["radius"])
        change = f"{100.0 * (r1 - r0) / r0:+.0f} %" if r0 > 0 else "n/a"
        lines.append(
            f"certified radius ({key.removeprefix('exact_map_')} slice, exact map, nominal loop, proved): "
            f"initial {r0:.4g} -> tuned {r1:.4g} ({change})"
        )
    pc, req = radii.get("problem_certificate"), radii.get("requirement")
    for basis in Slice if pc is not None else ():
        b0, b1 = pc["initial"][basis], pc["tuned"][basis]
        if b0["radius"] is None or b1["radius"] is None:
            continue
        change = f"{100.0 * (b1['radius'] - b0['radius']) / b0['radius']:+.0f} %" if b0["radius"] > 0 else "n/a"
        kept = req is not None and req["slice"] == basis and req["kind"] == "proved" and req["covers"] == b1["covers"]
        lines.append(
            f"certified radius ({basis} slice, the problem's loop: {', '.join(b1['covers'])}, {b1['kind']}): "
            f"initial {b0['radius']:.4g} -> tuned {b1['radius']:.4g} ({change}); "
            + ("kept by the requirement" if kept else "not kept by the tuner")
        )
    if req is not None:
        lines.append(
            f"requirement ({req['slice']} slice, {req['measured_by']}; covers {', '.join(req['covers'])}"
            + (f"; not {', '.join(req['not_covered'])}" if req["not_covered"] else "")
            + f"): {req['required_radius']:.4g}, the run's smallest accepted radius {req['smallest_radius_of_the_run']:.4g}, "
            f"tuned {req['tuned_radius']:.4g} ({req['kind']}): " + ("held" if req["held"] else "NOT held")
        )
    loop = radii.get("problem_loop")
    if loop is not None and not loop["covered"]:
        lines.append(f"note: {loop['note']}")
    return lines


if __name__ == "__main__":
    sys.exit(main())
