"""Checking an exported control step (:mod:`wmrjax.export`) outside the library: compile the
generated C with the system's compiler and call it through ctypes, time it from C, reload the
serialized artifact in a fresh process in which wmrjax cannot be imported, and compare each with
the JAX step over a run. Used by ``wmrjax export`` and the benchmark."""

from __future__ import annotations

import ctypes
import json
import shutil
import subprocess
import sys
import tempfile
from pathlib import Path

import jax
import numpy as np

from wmrjax import _files as files
from wmrjax import export as X

C_FLAGS = ("-std=c99", "-Wall", "-Wextra", "-Werror", "-O2")
TIMED_CALLS = 20000  # C step calls timed (best of 5 rounds)


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
        """One control step of the compiled C at time ``t`` [s] from ``measured``: ``(command, new state,
        regularity)``."""
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
    data = directory / "run_for_reload.npz"
    np.savez(data, t=np.asarray(run.t), measured=np.asarray(run.measured), state0=np.asarray(run.initial_state))
    # -I (isolated): neither the working directory nor PYTHONPATH nor the user's site is on
    # sys.path, so no file lying in `directory` (a json.py) is imported in place of a module
    r = subprocess.run(
        [sys.executable, "-I", "-c", RELOAD, str(artifact), str(data)], capture_output=True, text=True, cwd=directory
    )
    data.unlink()
    if r.returncode:
        raise RuntimeError(f"the artifact did not reload in a fresh process:\n{r.stderr[-3000:]}")
    return json.loads(r.stdout)


def verify(step, run, *, period: float, directory: Path, cc: str | None) -> dict:
    """The export checked over one closed-loop run of the simulator (:func:`wmrjax.export.reference_run`;
    see the module's docstring): the largest relative differences, and the C step's time."""
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
    # every scratch file (the run's data, the shared library, the timing driver) is written, and
    # every process runs, in a private temporary directory: nothing found in the user's output
    # directory is run or imported, and nothing there is written through a link
    with tempfile.TemporaryDirectory(prefix="wmrjax-export-check-") as scratch:
        return _verify_in(step, run, cmd, st, reg, out, directory, Path(scratch), cc, period)


def _verify_in(
    step, run, cmd, st, reg, out: dict, directory: Path, scratch: Path, cc: str | None, period: float
) -> dict:
    """:func:`verify`'s checks of the written files, on copies in ``scratch``."""
    for name in (f"{step.name}.h", f"{step.name}.c", f"{step.name}.jax_export"):  # what write_export wrote
        shutil.copyfile(directory / name, scratch / name, follow_symlinks=False)
    art = reload_in_fresh_process(scratch / f"{step.name}.jax_export", run, scratch)
    out["artifact_vs_jax"] = max(
        relative_error(art["command"], cmd),
        relative_error(art["state"], st),
        relative_error(np.asarray(art["regularity"])[:, None], reg[:, None]),
    )
    out["artifact_imported_wmrjax"] = art["wmrjax_imported"]
    if cc is None:
        out["c"] = "skipped: no C compiler (--cc)"
        return out
    c = CStep(compile_shared(scratch / f"{step.name}.c", cc), step)
    ccmd, cst, creg = X.drive(c, run)
    out["c_vs_jax"] = max(
        relative_error(ccmd, cmd), relative_error(cst, st), relative_error(creg[:, None], reg[:, None])
    )
    out["c_seconds_per_step"] = time_c_step(
        scratch,
        step,
        np.asarray(run.measured)[0],
        np.asarray(run.initial_state),
        t0=float(run.t[0]),
        period=period,
        cc=cc,
    )
    return out


def write_export(step, directory: Path) -> list:
    """The C files, the artifact and the robot-loop example into ``directory``; their names."""
    written = []
    for fname, text in X.generate_c(step).items():
        files.write_bytes(directory / fname, text.encode())
        written.append(fname)
    files.write_bytes(directory / f"{step.name}.jax_export", X.export_artifact(step))
    return written + [f"{step.name}.jax_export"]
