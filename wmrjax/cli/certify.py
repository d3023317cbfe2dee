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
``problem_certificate`` gives, per slice, the radius a proof covers for it (input limits alone:
the smaller of the exact map's and the saturation-free radius, also with a geometry range the
robot's kinematics ignore; input-scale and geometry ranges with a continuous velocity-level
controller: the mismatch radius; a digital controller,
noise or mismatch at torque level: none yet, ``not_covered`` lists them) and that loop's
falsified radius, from its own runs; a nominal radius above it is printed as a warning, a
proved one above it is an alarm (exit status 1).

The problem's ``[certify]`` section sets eps, the sample counts and the map (see
``wmrjax/examples/section_6_1.toml``, the default); the problem options and ``--set`` change
it (``--set certify.eps=0.02``, ``--set certify.n_starts=0``).
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

from wmrjax.certify import Slice
from wmrjax.certify.job import CertifyReport, run, settings, setup
from wmrjax.cli import machine, options, problem_args, running

EMPIRICAL_GRID = 48  # radii per ray of certify.empirical_radius (its n_grid)


def _parser():
    """The job's options: the problem (:mod:`wmrjax.cli.problem_args`), the case, the devices."""
    p = options.parser(__doc__.splitlines()[0], "results/certify")
    problem_args.add_problem_options(p, default="section_6_1")
    p.add_argument("--case", default=None, help="the [[case]] to certify, when the problem has several")
    p.add_argument(
        "--devices",
        type=options.count,
        default=os.cpu_count() or 1,
        help="JAX host devices the batch simulations are spread over (one per core; sets XLA_FLAGS "
        "before JAX starts its backend)",
    )
    return p


def _report(r: CertifyReport, out: Path) -> int:
    """Prints the radii with what they cover, the falsified ones, the problem's certificate and the
    alarms; the exit status (1 on an alarm)."""
    s = r.summary()
    labels = s["radius_labels"]
    print("nominal continuous loop:")
    for k, lab in labels.items():
        v = s.get(k)
        radius = v.get("radius") if isinstance(v, dict) else v
        if radius is not None:
            print(f"  {k} {radius:.4f} ({lab['kind']})")
    pc = r.problem_certificate
    if pc["loop"] != ["nominal"]:
        print(f"problem's loop ({', '.join(pc['loop'])}):")
        for b in Slice:
            c = pc[b]
            proved = "none proved" if c["radius"] is None else f"{c['radius']:.4f} ({c['kind']})"
            falsified = "none found" if c["falsified_radius"] is None else f"{c['falsified_radius']:.4f} (estimated)"
            covered = (
                f"covers {', '.join(c['covers'])}"
                if c["radius"] is not None
                else f"not covered: {', '.join(c['not_covered'])}"
            )
            print(f"  {b}: certified radius {proved} ({covered}); falsified {falsified}")
            for line in _plant_lines(c):
                print(f"    {line}")
    print(f"wrote {out}/summary.json and slice_map.png in {r.wall_time_s:.0f} s")
    for msg in r.warnings:
        print(f"warning: {msg}", file=sys.stderr)
    for msg in r.alarms:  # a result that contradicts the theory is an error, not a certificate
        print(f"error: {msg}", file=sys.stderr)
    return 1 if r.alarms else 0


def _plant_lines(c: dict) -> list:
    """The console's lines under a slice's problem certificate: the proofs' own numbers."""
    out = []
    sf = c.get("saturation_free")
    if sf is not None:
        up = "none found" if sf["upper_bound"] is None else f"{sf['upper_bound']:.4f} (attained)"
        out.append(f"saturation-free radius {sf['lower_bound']:.4f} (proved), {up}")
    for feature, why in c.get("inert", {}).items():
        out.append(f"{feature} inert: {why}")
    mm = c.get("mismatch")
    if mm is not None:
        dev = "unbounded" if mm["deviation_bound"] is None else f"{mm['deviation_bound']:.4g}"
        out.append(
            f"mismatch radius {mm['lower_bound']:.4f} (proved over the plant's range; deviation from "
            f"the nominal loop <= {dev}, bound by {mm['bound_by']})"
        )
    hr = c.get("held_reach")
    if hr is not None:
        nxt = (
            ""
            if hr["failed_radius"] is None
            else f"; from {hr['failed_radius']:.4g}: {hr['reason']} at t = {hr['failed_at']:g} s"
        )
        radius = "none" if hr["radius"] <= 0 else f"{hr['radius']:.4f} (proved)"
        out.append(
            f"held reach {radius}: the sampled loop enclosed period by period, noise within "
            f"{hr['noise_multiple']:g} noise_std{nxt}"
        )
    return out


def main(argv=None) -> int:
    """Run ``wmrjax certify`` with ``argv`` (default: the process's arguments); return the exit status."""
    p = _parser()
    a = p.parse_args(argv)
    machine.configure_xla(a.devices)  # before JAX starts its backend
    try:
        machine.enable_x64()
        problem = problem_args.problem_from_args(a)
        cfg = settings(problem)
        setting, _, _ = setup(problem, a.case)
    except ValueError as e:
        p.error(str(e))
    # the largest batch: the empirical checks, the slice map, or every ray's grid of radii at once
    # (checked here: a batch too large otherwise aborts the process in the allocator, late)
    batch = max(cfg["n_empirical"], cfg["map_grid"] ** 2, (cfg["n_directions"] + 1) * EMPIRICAL_GRID)
    machine.check_horizon(p, t_final=setting.t_final, dt=setting.dt, batch=batch, saved_every=10)
    s = running.work(p, a, lambda progress: run(a.out, problem, a.case, progress=progress))
    return _report(s, a.out)


if __name__ == "__main__":
    sys.exit(main())
