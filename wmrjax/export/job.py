"""The export job (``wmrjax export``): the problem's controller as a C99 step and a
``jax.export`` artifact (:func:`wmrjax.export.control_step`, :func:`wmrjax.export.generate_c`,
:func:`wmrjax.export.export_artifact`), each checked against the
simulator over a run (:mod:`wmrjax.export.check`), with an example robot loop and
``summary.json``."""

from __future__ import annotations

import time
from pathlib import Path

import jax
import numpy as np

from wmrjax import _files as files
from wmrjax import export as X
from wmrjax.controllers import place
from wmrjax.export.check import C_FLAGS, verify, write_export


def initial_state(setting, params, index: int | None = None):
    """``(z0, index)``: the law's state at one of the problem's initial conditions: ``index``, or by
    default the smallest non-zero initial error (a transient, which the largest errors of a map
    may not survive)."""
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
    say = progress or (lambda msg: print(msg, flush=True))
    jax.config.update("jax_enable_x64", True)  # the job runs in float64
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
    files.write_json(out / "summary.json", summary)
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
