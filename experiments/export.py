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

import ctypes
import json
import shutil
import subprocess
import sys
import time
from pathlib import Path

from experiments import common

DEFAULT_PROBLEM = Path(__file__).resolve().parent / "problems" / "section_6_1.toml"
C_FLAGS = ("-std=c99", "-Wall", "-Wextra", "-Werror", "-O2")
DEFAULT_PERIOD = 0.01  # [s] of a problem without a digital controller ([plant] control_period)
TIMED_CALLS = 20000  # C step calls timed (best of 5 rounds)

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


def compile_shared(c_file: Path, cc: str = "cc") -> Path:
    """Compile generated C into a shared library next to it (``C_FLAGS``): ValueError with the
    compiler's messages when it fails (a warning is an error)."""
    lib = c_file.with_suffix(".so")
    r = subprocess.run(
        [cc, *C_FLAGS, "-shared", "-fPIC", str(c_file), "-o", str(lib), "-lm"], capture_output=True, text=True
    )
    if r.returncode:
        raise ValueError(f"{cc} refused {c_file.name} (flags {' '.join(C_FLAGS)}):\n{r.stderr[-3000:]}")
    return lib


class CStep:
    """The generated C step, loaded with ctypes: ``CStep(lib, step)(t, measured, state)``."""

    def __init__(self, lib: Path, step):
        self.lib = ctypes.CDLL(str(lib))
        self.fn = getattr(self.lib, f"{step.name}_step")
        self.n_command = step.n_command
        self._d = ctypes.POINTER(ctypes.c_double)

    def __call__(self, t, measured, state):
        import numpy as np

        m = np.ascontiguousarray(measured, np.float64)
        s = np.array(state, np.float64)  # updated in place: a copy
        c = np.zeros(self.n_command)
        r = ctypes.c_double()
        self.fn(
            ctypes.c_double(t),
            m.ctypes.data_as(self._d),
            s.ctypes.data_as(self._d),
            c.ctypes.data_as(self._d),
            ctypes.byref(r),
        )
        return c, s, r.value


def relative_error(a, b) -> float:
    """Largest ``|a - b|`` over a run, relative to the largest ``|b|`` of that output over the run
    (all its components: a component that stays at rounding level, e.g. a turn rate on a straight
    path, is measured against the output's scale, not its own); 0 for empty outputs."""
    import numpy as np

    a, b = np.asarray(a, float), np.asarray(b, float)
    if a.size == 0:
        return 0.0
    scale = float(np.max(np.abs(b)))
    return float(np.max(np.abs(a - b))) / (scale if scale > 0 else 1.0)


TIMER = r"""#define _POSIX_C_SOURCE 199309L
#include <stdio.h>
#include <time.h>
#include "{name}.h"
static const double measured0[{n_m}] = {measured};
static const double state0[{n_s1}] = {state};
int main(void) {{
    double measured[{n_m}], state[{n_s1}], command[{n_c}], regularity, sink = 0.0, best = 1e30, t;
    long i; int round, k;
    for (round = 0; round < {rounds}; ++round) {{
        struct timespec a, b;
        for (k = 0; k < {n_m}; ++k) measured[k] = measured0[k];
        for (k = 0; k < {n_s1}; ++k) state[k] = state0[k];
        t = {t0};
        clock_gettime(CLOCK_MONOTONIC, &a);
        for (i = 0; i < {calls}; ++i) {{
            measured[0] += 1e-9;                      /* a new measurement each period */
            {name}_step(t, measured, state, command, &regularity);
            sink += command[0] + regularity;
            t += {period};
        }}
        clock_gettime(CLOCK_MONOTONIC, &b);
        {{ double s = (b.tv_sec - a.tv_sec) + 1e-9 * (b.tv_nsec - a.tv_nsec); if (s < best) best = s; }}
    }}
    printf("%.17g %.17g\n", best / {calls}, sink);
    return 0;
}}
"""


def time_c_step(
    directory: Path, step, measured, state, *, t0: float, period: float, cc: str = "cc", rounds: int = 5
) -> float:
    """Seconds per call of the generated C step, timed from C (a driver compiled with the step at
    ``C_FLAGS``; best of ``rounds`` loops of :data:`TIMED_CALLS` periods from ``measured``/``state``)."""
    fmt = lambda xs: "{" + ", ".join(repr(float(x)) for x in list(xs) or [0.0]) + "}"
    src = directory / "time_step.c"
    src.write_text(
        TIMER.format(
            name=step.name, n_m=step.n_measured, n_s1=step.n_state + 1, n_c=step.n_command,
            measured=fmt(measured), state=fmt(list(state) + [0.0]), rounds=rounds, calls=TIMED_CALLS,
            t0=repr(float(t0)), period=repr(float(period)),
        )
    )  # fmt: skip
    exe = directory / "time_step"
    r = subprocess.run(
        [cc, *C_FLAGS, str(src), str(directory / f"{step.name}.c"), "-o", str(exe), "-lm"],
        capture_output=True,
        text=True,
    )
    if r.returncode:
        raise ValueError(f"{cc} refused the timing driver:\n{r.stderr[-3000:]}")
    out = subprocess.run([str(exe)], capture_output=True, text=True, check=True).stdout.split()
    src.unlink(), exe.unlink()
    return float(out[0])


RELOAD = r"""
import json, sys
sys.modules["wmrjax"] = None  # wmrjax cannot be imported here: the artifact must run without it
import numpy as np
import jax
jax.config.update("jax_enable_x64", True)
data = np.load(sys.argv[2])
exp = jax.export.deserialize(bytearray(open(sys.argv[1], "rb").read()))
state, out = data["state0"], {"command": [], "state": [], "regularity": []}
for t, m in zip(data["t"], data["measured"]):
    c, state, r = (np.asarray(x) for x in exp.call(t, m, state))
    out["command"].append(c.tolist()), out["state"].append(state.tolist()), out["regularity"].append(float(r))
out["wmrjax_imported"] = any(k.startswith("wmrjax.") for k in sys.modules) or sys.modules["wmrjax"] is not None
print(json.dumps(out))
"""


def reload_in_fresh_process(artifact: Path, run, directory: Path) -> dict:
    """Drive the serialized artifact over ``run`` in a new Python process that imports jax and
    NumPy only (its ``wmrjax_imported`` says whether anything imported wmrjax)."""
    import numpy as np

    data = directory / "run_for_reload.npz"
    np.savez(data, t=np.asarray(run.t), measured=np.asarray(run.measured), state0=np.asarray(run.initial_state))
    r = subprocess.run(
        [sys.executable, "-c", RELOAD, str(artifact), str(data)], capture_output=True, text=True, cwd=directory
    )
    data.unlink()
    if r.returncode:
        raise RuntimeError(f"the artifact did not reload in a fresh process:\n{r.stderr[-3000:]}")
    return json.loads(r.stdout)


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
    if not 0 <= index < len(errors):
        raise ValueError(
            f"--initial {index}: the problem has {len(errors)} initial conditions (0 to {len(errors) - 1})"
        )
    branch = setting.branch[0] if len(setting.branch) else 1.0
    return place(setting.ctrl, params, errors[index], setting.space, setting.task, branch), index


def verify(step, run, *, period: float, directory: Path, cc: str | None) -> dict:
    """The export checked over one closed-loop run of the simulator (:func:`wmrjax.export.reference_run`;
    see the module's docstring): the largest relative differences, and the C step's time."""
    import jax
    import numpy as np

    from wmrjax import export as X

    cmd, st, reg = X.drive(jax.jit(step.fn), run)
    # the step at each sample from the simulator's own controller state: the same computation
    per_sample = jax.jit(jax.vmap(step.fn))(run.t, run.measured, run.state)[0]
    out = {
        "samples": len(run.t),
        "run_complete": run.complete,
        "period_s": period,
        "jax_vs_simulator": relative_error(per_sample, run.command),
        "jax_driven_vs_simulator": relative_error(cmd, run.command),
    }
    art = reload_in_fresh_process(directory / f"{step.name}.jax_export", run, directory)
    out["artifact_vs_jax"] = max(
        relative_error(art["command"], cmd),
        relative_error(art["state"], st),
        relative_error(np.asarray(art["regularity"])[:, None], reg[:, None]),
    )
    out["artifact_imported_wmrjax"] = art["wmrjax_imported"]
    if cc is None:
        out["c"] = "skipped: no C compiler (--cc)"
        return out
    c = CStep(compile_shared(directory / f"{step.name}.c", cc), step)
    ccmd, cst, creg = X.drive(c, run)
    out["c_vs_jax"] = max(
        relative_error(ccmd, cmd), relative_error(cst, st), relative_error(creg[:, None], reg[:, None])
    )
    out["c_seconds_per_step"] = time_c_step(
        directory,
        step,
        np.asarray(run.measured)[0],
        np.asarray(run.initial_state),
        t0=float(run.t[0]),
        period=period,
        cc=cc,
    )
    (directory / f"{step.name}.so").unlink()
    return out


def write_export(step, directory: Path) -> list:
    """The C files, the artifact and the robot-loop example into ``directory``; their names."""
    from wmrjax import export as X
    from wmrjax_cli import files

    written = []
    for fname, text in X.generate_c(step).items():
        files.write_bytes(directory / fname, text.encode())
        written.append(fname)
    files.write_bytes(directory / f"{step.name}.jax_export", X.export_artifact(step))
    return written + [f"{step.name}.jax_export"]


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
    cc = None if a.cc == "none" else a.cc
    if cc is not None and shutil.which(cc) is None:
        options.fail(p, f"--cc {a.cc}: no such compiler on PATH (give another, or --cc none to skip the C checks)")
    try:
        common.enable_x64()
        problem = Problem.load(a.file if a.file is not None else DEFAULT_PROBLEM)
        if a.gains is not None:
            problem = problem.with_values({"gains": {"file": str(a.gains.resolve())}})
        setup(problem, a.case)
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
