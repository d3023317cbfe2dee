r"""Export a problem's controller for the robot: its control step as a jax.export artifact and as C99.

    wmrjax export wmrjax/examples/s_path.toml --gains results/s_path/tune/gains.json \
        --out results/s_path/export

Writes into ``--out``: ``<name>.h`` and ``<name>.c`` (C99, ``math.h`` only: the law with the
problem's reference and gains, see :mod:`wmrjax.export`), ``<name>.jax_export`` (the serialized
``jax.export`` artifact, float64, CPU), ``robot_loop.c`` (the loop a robot runs, as an example
that compiles against the generated code), and ``summary.json``. Before writing it checks the
export: a closed-loop run of the simulator's digital controller from the problem's first
initial condition (no noise, no limits), the JAX step driven over the run's measurements
against the simulator's commands, the generated C (compiled with ``--cc``, ``-std=c99 -Wall
-Wextra -Werror -O2``) and the reloaded artifact against the JAX step, each as the largest
difference relative to the largest magnitude of each output over the run; and it times the C
step. A disagreement above ``--tolerance`` is an error (exit status 1).
"""

from __future__ import annotations

import shutil
import sys

from wmrjax.cli import machine, options, problem_args, running
from wmrjax.export.job import DEFAULT_PERIOD, check_initial, run, setup


def _parser():
    p = options.parser(__doc__.splitlines()[0], "results/export")
    problem_args.add_problem_options(p, default="section_6_1")
    p.add_argument("--case", default=None, help="the [[case]] to export, when the problem has several")
    p.add_argument(
        "--period",
        type=options.positive,
        default=None,
        help=f"controller period [s] (default: the problem's [plant] control_period, else {DEFAULT_PERIOD})",
    )
    p.add_argument(
        "--samples", type=options.count, default=None, help="periods of the checked run (default: the horizon)"
    )
    p.add_argument(
        "--initial",
        type=int,
        default=None,
        help="which of the problem's initial conditions starts the checked run (default: the smallest non-zero error)",
    )
    p.add_argument("--cc", default="cc", help="the C compiler that checks and times the generated code ('none': skip)")
    p.add_argument("--tolerance", type=options.positive, default=1e-12, help="largest relative disagreement accepted")
    return p


def main(argv=None) -> int:
    """Run ``wmrjax export`` with ``argv`` (default: the process's arguments); return the exit status."""
    p = _parser()
    a = p.parse_args(argv)
    machine.configure_xla()  # before JAX starts its backend
    cc = None if a.cc == "none" else a.cc
    if cc is not None and shutil.which(cc) is None:
        options.fail(p, f"--cc {a.cc}: no such compiler on PATH (give another, or --cc none to skip the C checks)")
    try:
        machine.enable_x64()
        problem = problem_args.problem_from_args(a)
        setting, _, _ = setup(problem, a.case)
        if a.initial is not None:  # refused here, before the export's work, not after
            check_initial(setting, a.initial)
    except ValueError as e:
        p.error(str(e))
    r = running.work(
        p,
        a,
        lambda progress: run(
            a.out,
            problem,
            case=a.case,
            period=a.period,
            n_samples=a.samples,
            initial=a.initial,
            cc=cc,
            tolerance=a.tolerance,
            progress=progress,
        ),
    )
    c = r.checks
    print(
        f"{r.step.name}: JAX step vs simulator {c['jax_vs_simulator']:.1e}, artifact vs JAX {c['artifact_vs_jax']:.1e}"
        + (f", C vs JAX {c['c_vs_jax']:.1e}, C step {c['c_seconds_per_step'] * 1e9:.0f} ns" if "c_vs_jax" in c else "")
        + f"; wrote {a.out}"
    )
    if not r.agrees:
        print(
            f"error: the export disagrees with the simulator beyond {a.tolerance} (see summary.json checks)",
            file=sys.stderr,
        )
        return 1
    return 0


if __name__ == "__main__":
    sys.exit(main())
