r"""Export a problem's controller for the robot: its control step as a jax.export artifact and as C99.

    python -m experiments.export experiments/problems/s_path.toml --gains results/s_path/tune/gains.json \
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
import time
from pathlib import Path

from experiments import common
from wmrjax_cli.export_check import C_FLAGS, verify, write_export

DEFAULT_PROBLEM = Path(__file__).resolve().parent / "problems" / "section_6_1.toml"
DEFAULT_PERIOD = 0.01  # [s] of a problem without a digital controller ([plant] control_period)

ROBOT_LOOP = r"""/* The loop a robot runs with the generated controller (an example: replace the two stubs).
 * Build: cc -std=c99 -O2 robot_loop.c {name}.c -lm */
#include <stdio.h>
#include "{name}.h"

/* stubs: the robot's clock, sensors and actuators */
static double t_now = 0.0;
static const double measured0[{upper}_N_MEASURED] = {measured0};   /* the first measurement of the checked run */
static void read_sensors(double *measured) {{ int i; for (i = 0; i < {upper}_N_MEASURED; ++i) measured[i] = measured0[i]; }}
static void apply_command(const double *command) {{ (void)command; }}

int main(void) {{
    double measured[{upper}_N_MEASURED], command[{upper}_N_COMMAND], regularity;
    double state[{upper}_N_STATE + 1];               /* + 1: a static law's state is empty */
    const double compensator0[{upper}_N_COMPENSATOR + 1] = {compensator0};
    int k;
    {name}_init(t_now, compensator0, state);
    for (k = 0; k < 10; ++k) {{                       /* every controller period ({period} s) */
        read_sensors(measured);
        {name}_step(t_now, measured, state, command, &regularity);
        apply_command(command);                       /* held until the next period */
        t_now += {period};
    }}
    printf("command after %d periods: %g (regularity %g)\n", k, command[0], regularity);
    return 0;
}}
"""


def initial_state(setting, params, index: int | None = None):
    """``(z0, index)``: the law's state at one of the problem's initial conditions: ``index``, or by
    default the smallest non-zero initial error (a transient, which the largest errors of a map
    may not survive)."""
    import numpy as np

    from wmrjax.problem import place

    errors = setting.initial_errors()
    if index is None:
        norms = np.linalg.norm(errors, axis=1)
        nonzero = np.flatnonzero(norms > 0)
        index = int(nonzero[np.argmin(norms[nonzero])]) if nonzero.size else 0
    check_initial(setting, index)
    branch = setting.branch[0] if len(setting.branch) else 1.0
    return place(setting.ctrl, params, errors[index], setting.space, setting.task, branch), index


def check_initial(setting, index: int) -> None:
    """ValueError unless ``index`` names one of the problem's initial conditions (``--initial``)."""
    n = len(setting.initial_errors())
    if not 0 <= index < n:
        raise ValueError(f"--initial {index}: the problem has {n} initial conditions (0 to {n - 1})")


def setup(problem, case=None):
    """``(setting, ctrl, params)`` of the problem's one controller (one geometry, reference and gains)."""
    setting = problem.setting("export", case=case)
    setting.check_single("export", keep=("initial", "plant"))
    return setting, setting.ctrl, setting.params()


def run(
    out: Path, problem, *, case=None, period=None, n_samples=None, initial=None, cc="cc", tolerance=1e-12, progress=None
) -> dict:
    """Export and check the problem's controller; writes the files and ``summary.json`` into ``out``."""
    import numpy as np

    from wmrjax import export as X
    from wmrjax_cli import files

    say = progress or (lambda msg: print(msg, flush=True))
    common.enable_x64()
    t0 = time.time()
    setting, ctrl, params = setup(problem, case)
    period = period or setting.control_period or DEFAULT_PERIOD
    n_samples = n_samples or max(1, int(round(setting.t_final / period)))
    step = X.control_step(ctrl, params)
    say(f"export {ctrl.robot.name} ({ctrl.level}) along {setting.reference.name} as {step.name}")
    out.mkdir(parents=True, exist_ok=True)
    # a previous export's summary describes its own code: gone before the new code is written,
    # so a run killed in between leaves no summary saying "agrees" beside code it never checked
    (out / "summary.json").unlink(missing_ok=True)
    written = write_export(step, out)
    z0, index = initial_state(setting, params, initial)
    say(f"check: {n_samples} periods of {period} s against the simulator")
    sim = X.reference_run(step, ctrl, params, z0, period=period, n_samples=n_samples)
    comp0 = np.asarray(sim.initial_state)[: step.n_compensator]
    files.write_bytes(out / "robot_loop.c", _robot_loop(step, np.asarray(sim.measured)[0], comp0, period).encode())
    checks = verify(step, sim, period=period, directory=out, cc=cc)
    # the driven step carries its own compensator, which leaves the simulator's by rounding: reported only
    worst = max(v for k, v in checks.items() if k in ("jax_vs_simulator", "artifact_vs_jax", "c_vs_jax"))
    summary = {
        "experiment": "export",
        "problem_name": problem.title,
        "case": case,
        "problem": problem.resolved(),
        "gains": problem.resolved().get("gains"),
        "name": step.name,
        "robot": step.robot,
        "level": step.level,
        "reference": setting.reference.name,
        # [s] where a sampled path's data define it; outside, the step's regularity is 0 (stop)
        "reference_span_s": X.reference_span(params.reference),
        "sizes": {
            "measured": step.n_measured,
            "state": step.n_state,
            "command": step.n_command,
            "compensator": step.n_compensator,
        },
        "names": {
            "measured": step.measured_names,
            "command": step.command_names,
            "compensator": step.compensator_names,
        },
        "files": written + ["robot_loop.c"],
        "initial_condition": {"index": index, "error": setting.initial_errors()[index].tolist()},
        "initial_compensator": comp0.tolist(),
        "checks": checks,
        "tolerance": tolerance,
        "agrees": bool(worst <= tolerance) and not checks["artifact_imported_wmrjax"],
        "c_compiler": cc,
        "c_flags": list(C_FLAGS),
        "wall_time_s": time.time() - t0,
    }
    common.write_json(out / "summary.json", summary)
    return summary


def _robot_loop(step, measured0, comp0, period) -> str:
    fmt = lambda xs: "{" + ", ".join(repr(float(x)) for x in list(xs) or [0.0]) + "}"
    return ROBOT_LOOP.format(
        name=step.name,
        upper=step.name.upper(),
        measured0=fmt(measured0),
        compensator0=fmt(comp0),
        period=repr(float(period)),
    )


def _parser():
    from wmrjax_cli import options

    p = common.parser(__doc__.splitlines()[0], "results/export")
    p.add_argument("file", type=Path, nargs="?", default=None, help="a problem file (TOML; default: section 6.1)")
    p.add_argument("--case", default=None, help="the [[case]] to export, when the problem has several")
    p.add_argument("--gains", type=Path, default=None, help="a tuned-gains file (gains.json of python -m tuning)")
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
    from wmrjax.problem import Problem
    from wmrjax_cli import options

    p = _parser()
    a = p.parse_args(argv)
    options.configure_xla()  # before JAX starts its backend
    cc = None if a.cc == "none" else a.cc
    if cc is not None and shutil.which(cc) is None:
        options.fail(p, f"--cc {a.cc}: no such compiler on PATH (give another, or --cc none to skip the C checks)")
    try:
        common.enable_x64()
        problem = Problem.load(a.file if a.file is not None else DEFAULT_PROBLEM)
        if a.gains is not None:
            problem = problem.with_values({"gains": {"file": str(a.gains.resolve())}})
        setting, _, _ = setup(problem, a.case)
        if a.initial is not None:  # refused here, before the export's work, not after
            check_initial(setting, a.initial)
    except ValueError as e:
        p.error(str(e))
    s = options.work(
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
    c = s["checks"]
    print(
        f"{s['name']}: JAX step vs simulator {c['jax_vs_simulator']:.1e}, artifact vs JAX {c['artifact_vs_jax']:.1e}"
        + (f", C vs JAX {c['c_vs_jax']:.1e}, C step {c['c_seconds_per_step'] * 1e9:.0f} ns" if "c_vs_jax" in c else "")
        + f"; wrote {a.out}"
    )
    if not s["agrees"]:
        print(
            f"error: the export disagrees with the simulator beyond {a.tolerance} (see summary.json checks)",
            file=sys.stderr,
        )
        return 1
    return 0


if __name__ == "__main__":
    sys.exit(main())
