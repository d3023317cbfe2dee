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

from wmrjax import certify as C
from wmrjax.certify.plant_table import run
from wmrjax.cli import machine, options, problem_args, running


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
    r = running.work(p, a, lambda progress: run(a.out, problem, a.slice, progress=progress))
    print(f"nominal {r.slice}-slice radius {r.nominal.lower_bound:.4f} (proved), eps = {r.eps}:")
    print(r.markdown())
    return 0


if __name__ == "__main__":
    sys.exit(main())
