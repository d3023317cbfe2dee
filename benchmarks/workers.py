"""The benchmark's measurements that need a fresh process, as functions (issue 55: no code inside
strings). Run by path, ``python benchmarks/workers.py WORKER ARGS...``, with the ``wmrjax`` to
measure first on ``PYTHONPATH`` (this checkout's, or another commit's for a side-by-side ratio):
the file imports nothing of the repository but ``wmrjax``. Each prints one JSON line.

Workers:
  ``tuner NAME``: the tuning loop's gradient program on a shipped problem: trace, XLA compile and
  step (best of 3 rounds of 5 calls), with no persistent compilation cache.
  ``simulate N DT``, ``tune``, ``sweep SPEC OUT``: the peak resident memory's growth (VmHWM) of
  one run of N steps, of a tuning step from 64 to 2048 scenarios, and of a sweep, with the
  memory model's prediction (``measured``, ``predicted``).
"""

from __future__ import annotations

import json
import sys
import time

import jax

from wmrjax.cli import machine

jax.config.update("jax_enable_x64", True)

# each worker imports the wmrjax modules it measures inside it: the file runs against another
# commit's wmrjax too, which may lack a module another worker needs


def peak() -> int:
    """The peak resident memory of this process image [bytes] (VmHWM: ru_maxrss would carry a
    parent's peak over fork and exec; a pytest worker's 2 GB hid the child's growth)."""
    with open("/proc/self/status") as f:
        for line in f:
            if line.startswith("VmHWM:"):
                return int(line.split()[1]) * 1024
    raise RuntimeError("no VmHWM in /proc/self/status (a Linux kernel is needed)")


def tuner(name: str) -> dict:
    """Trace, compile and step times of the tuner's gradient program on the shipped problem ``name``."""
    t_start = time.perf_counter()  # setup_s: the imports, the problem, the scenarios
    from wmrjax.examples import problem_file
    from wmrjax.problem import Problem
    from wmrjax.tune import config
    from wmrjax.tune import loop as L

    problem = Problem.load(problem_file(name))
    s = problem.setting("tuning")
    ts = config.read(problem.section("tune"))
    fam = ts.gain_family(s)
    ctx = L.prepare(s, fam, ts.scenarios, ts.loss, ts.seed)
    args, static = (L.initial_raw(s, fam), ctx.sets.train, s, fam, ctx.weights), (2, 3)
    t_ready = time.perf_counter()
    lowered = L._gradient_step.lower(*args)
    t_traced = time.perf_counter()
    compiled = lowered.compile()
    t_compiled = time.perf_counter()
    dyn = [a for i, a in enumerate(args) if i not in static]
    jax.block_until_ready(compiled(*dyn))
    best = float("inf")
    for _ in range(3):
        t = time.perf_counter()
        for _ in range(5):
            out = compiled(*dyn)
        jax.block_until_ready(out)
        best = min(best, (time.perf_counter() - t) / 5)
    return {
        "problem": name,
        "setup_s": t_ready - t_start,
        "trace_s": t_traced - t_ready,
        "compile_s": t_compiled - t_traced,
        "step_s": best,
        "loss": float(out[0]),
    }


def simulate(n: int, dt: float) -> dict:
    """The memory of one run of ``n`` RK4 steps of ``dt`` [s] (the §6.1 circle), and its prediction."""
    import wmrjax as w
    from wmrjax import references as R
    from wmrjax import resources

    ctrl = w.dynamic_linearization("(2,0)", "velocity")
    p = ctrl.params(R.circle(radius=3.0, omega=0.5), poles=1.0)
    z0 = ctrl.initial_state(ctrl.reference_jet(0.0, p)[:2] + 0.05, p)
    w.simulate(ctrl, z0, p, dt=0.01, n_steps=10)
    base = peak()
    jax.block_until_ready(w.simulate(ctrl, z0, p, dt=dt, n_steps=n))
    est = resources.run_estimate(ctrl, n_steps=n, save_every=1, n_state=4, itemsize=8, horizon=n * dt)
    return {"measured": peak() - base, "predicted": est.total}


def tune() -> dict:
    """The memory a tuning step grows by from 64 to 2048 training scenarios, and its prediction."""
    from wmrjax import resources
    from wmrjax.problem import Problem
    from wmrjax.tune import config, loop

    prob = Problem.load("wmrjax/examples/section_6_1_plant.toml")
    setting = prob.setting("tuning")
    ts = config.read(prob.section("tune"))
    fam = ts.gain_family(setting)
    peaks = []
    for n in (64, 2048):
        sc = ts.scenarios._replace(train=n, validation=4, heldout=4)
        loop.tune(
            setting,
            fam,
            ts.optimizer.build(1),
            steps=1,
            scenarios=sc,
            loss=ts.loss,
            stopping=ts.stopping,
            log=lambda *_: None,
        )
        peaks.append(peak())
    n_state, n_steps = setting.system().n_state, setting.n_steps
    pred = resources.gradient_bytes(2048, n_steps, n_state) - resources.gradient_bytes(64, n_steps, n_state)
    return {"measured": peaks[1] - peaks[0], "predicted": pred}


def sweep(spec: str, out: str) -> dict:
    """The peak memory of ``wmrjax sweep SPEC --out OUT`` on one device, and the sweep's prediction."""
    from wmrjax.cli import sweep as cli
    from wmrjax.sweep import run
    from wmrjax.sweep import spec as S

    rc = cli.main([spec, "--out", out, "--devices", "1", "--no-compile-cache"])
    return {"measured": peak(), "predicted": run.estimate(S.load(spec), 1).total, "rc": rc}


WORKERS = {
    "tuner": (tuner, (str,)),
    "simulate": (simulate, (int, float)),
    "tune": (tune, ()),
    "sweep": (sweep, (str, str)),
}


def main(argv: list) -> int:
    """Run the worker ``argv[0]`` with the arguments after it; print its JSON line."""
    if not argv or argv[0] not in WORKERS:
        raise SystemExit(f"usage: workers.py {{{','.join(WORKERS)}}} ARGS... (got {argv})")
    fn, types = WORKERS[argv[0]]
    if len(argv) - 1 != len(types):
        raise SystemExit(f"{argv[0]} takes {len(types)} argument(s), got {argv[1:]}")
    machine.configure_xla()  # the command lines' XLA:CPU settings, before JAX's backend starts
    print(json.dumps(fn(*(t(a) for t, a in zip(types, argv[1:])))))
    return 0


if __name__ == "__main__":
    sys.exit(main(sys.argv[1:]))
