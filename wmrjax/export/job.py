"""The export job (``wmrjax export``): the problem's controller as a C99 step and a
``jax.export`` artifact (:func:`wmrjax.export.control_step`, :func:`wmrjax.export.generate_c`,
:func:`wmrjax.export.export_artifact`), each checked against the
simulator over a run (:mod:`wmrjax.export.check`), with an example robot loop and
``summary.json``."""

from __future__ import annotations

import dataclasses
import time
from pathlib import Path

import jax
import numpy as np

from wmrjax import _files as files
from wmrjax import export as X
from wmrjax.controllers import place
from wmrjax.export.check import C_FLAGS, verify, write_export
from wmrjax.problem import Problem, Setting
from wmrjax.report import JobReport


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
    branch = float(setting.branch[0]) if len(setting.branch) else 1.0  # +-1.0 (the problem holds ints)
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


@dataclasses.dataclass(frozen=True)
class ExportReport(JobReport):
    """What :func:`run` wrote and how well it agrees with the simulator.

    Attributes:
        problem: the problem exported.
        case: its case (``None``: the problem has none).
        setting: the problem's one closed loop (:meth:`wmrjax.problem.Problem.setting`).
        step: the exported step (:class:`wmrjax.export.ControlStep`: its name, sizes and signal names).
        files: the files written into the output directory, ``summary.json`` aside.
        initial_index: the initial condition the check ran from (an index into the problem's).
        initial_compensator: ``(n_compensator,)`` the law's compensator at that condition.
        checks: each comparison's largest difference (``jax_vs_simulator``, ``artifact_vs_jax``,
            ``c_vs_jax``, ...) and whether the artifact imported wmrjax (``artifact_imported_wmrjax``).
        tolerance: the largest difference accepted.
        c_compiler: the C compiler used.
        wall_time_s: the job's wall time [s].
    """

    problem: Problem
    case: str | None
    setting: Setting
    step: X.ControlStep
    files: tuple
    initial_index: int
    initial_compensator: np.ndarray
    checks: dict
    tolerance: float
    c_compiler: str
    wall_time_s: float

    @property
    def agrees(self) -> bool:
        """Whether the JAX step, the artifact and the C step agree with the simulator within
        :attr:`tolerance` and the artifact runs without wmrjax (the driven step carries its own
        compensator, which leaves the simulator's by rounding: reported only)."""
        compared = ("jax_vs_simulator", "artifact_vs_jax", "c_vs_jax")
        worst = max(v for k, v in self.checks.items() if k in compared)
        return bool(worst <= self.tolerance) and not self.checks["artifact_imported_wmrjax"]

    def summary(self) -> dict:
        """``summary.json`` (plain JSON)."""
        step, setting, resolved = self.step, self.setting, self.problem.resolved()
        return files.jsonable(
            {
                "experiment": "export",
                "problem_name": self.problem.title,
                "case": self.case,
                "problem": resolved,
                "gains": resolved.get("gains"),
                "name": step.name,
                "robot": step.robot,
                "level": step.level,
                "reference": setting.reference.name,
                # [s] where a sampled path's data define it; outside, the step's regularity is 0 (stop)
                "reference_span_s": step.span,
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
                "files": list(self.files),
                "initial_condition": {
                    "index": self.initial_index,
                    "error": setting.initial_errors()[self.initial_index].tolist(),
                },
                "initial_compensator": self.initial_compensator.tolist(),
                "checks": self.checks,
                "tolerance": self.tolerance,
                "agrees": self.agrees,
                "c_compiler": self.c_compiler,
                "c_flags": list(C_FLAGS),
                "wall_time_s": self.wall_time_s,
            }
        )


def run(
    out: Path, problem, *, case=None, period=None, n_samples=None, initial=None, cc="cc", tolerance=1e-12, progress=None
) -> ExportReport:
    """Export and check the problem's controller; writes the files and ``summary.json`` into ``out``.

    Args:
        out: the output directory (``Path``; made if missing).
        problem: the problem (:class:`wmrjax.problem.Problem`) with one controller.
        case: the case to export, for a problem with cases.
        period: the controller period of the check [s] (default: the problem's, else
            :data:`DEFAULT_PERIOD`).
        n_samples: the periods checked (default: the problem's horizon).
        initial: the index of the initial condition checked (default: :func:`initial_state`'s).
        cc: the C compiler.
        tolerance: the largest difference accepted.
        progress: called with each progress message (default: printed).

    Returns:
        the :class:`ExportReport`.
    """
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
    report = ExportReport(
        problem, case, setting, step, (*written, "robot_loop.c"), index, comp0, checks, tolerance, cc, time.time() - t0
    )
    report.write_summary(out)
    return report


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
