"""Identification from logs (issue 56): do the 95 % intervals cover the truth, and how long does a
fit take?

    python -m benchmarks.identify [--seeds 50] [--record]

1. Coverage. For (2,0) and (1,1) at velocity level and (1,1) at torque level, ``--seeds`` logs
   (10 s at 50 Hz, one log per fit) integrated by SciPy's DOP853 from known parameters with
   Gaussian measurement noise (``tests/identify_oracle.py``: the tests' own integration, not
   ``wmrjax.simulate``) are fitted; per parameter: how often the 95 % interval covers the truth,
   and the spread of (estimate - truth) / standard error over the seeds (repeated logs from the
   true parameters, a parametric bootstrap at the truth: 1 if the standard errors are right;
   each seed draws its own commands, so the mean standard error and the estimates' spread are
   shown beside it but do not compare one to one).
2. Bootstrap. Per robot one log fitted, then ``--replicates`` logs integrated by SciPy from the
   *fitted* parameters and noise (the same commands, new noise), each fitted: the spread of their
   estimates against the first fit's standard errors.
3. Time. A 30 s, 50 Hz log of the (1,1) car of ``wmrjax/examples/car_waypoints.toml``
   (torque level) fitted in a fresh process: the fit's wall time cold (compilation included),
   and warm (a second fit of the same shapes).

Writes ``identify.json`` into ``--out`` and prints the tables; ``--record``: the page's record too
(``benchmarks/records/identify.json``, rendered into docs/benchmarks.md by :mod:`benchmarks.page`).
"""

from __future__ import annotations

import argparse
import json
import os
import subprocess
import sys
import time
from pathlib import Path

import jax
import numpy as np

import wmrjax as w
from benchmarks import page
from wmrjax import identify
from wmrjax.cli import machine
from wmrjax.controllers.law import Level
from wmrjax.problem import Problem

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT / "tests"))  # the oracle is the tests' own SciPy integration, on purpose
from identify_oracle import make_log  # noqa: E402 - found through the line above

CONFIGS = (
    ("(2,0)", "velocity", 1.0, [1.08, 0.94], [0.01, 0.01, 0.005]),
    ("(1,1)", "velocity", 1.06, [0.92, 1.04], [0.01, 0.01, 0.005, 0.005]),
    ("(1,1)", "torque", 1.06, [0.92, 1.04], [0.01, 0.01, 0.005, 0.005]),
)
PERIOD, L = 0.02, 0.33


def _model(kind: str, level: str):
    return identify.PlantModel(w.robot_type(kind), Level(level), w.Geometry(L, 0.25, 0.0), (np.inf, np.inf), PERIOD)


def _log(kind, level, geometry_scale, scales, noise, seed, noise_seed=None, n=501):
    """A log of ``n`` samples at 50 Hz (10 s by default) integrated by SciPy (the oracle)."""
    return make_log(
        kind, level, L=L, geometry_scale=geometry_scale, input_scale=scales, noise_std=noise, n=n, period=PERIOD,
        seed=seed, noise_seed=noise_seed,
    )  # fmt: skip


def coverage(seeds: int) -> list:
    rows = []
    for kind, level, gs, scales, noise in CONFIGS:
        model = _model(kind, level)
        truth = {"geometry_scale": gs, **{f"input_scale_{i + 1}": s for i, s in enumerate(scales)}}
        truth |= {f"noise_std_{c}": s for c, s in zip(model.channels, noise)}
        est = {k: [] for k in truth}
        t0 = time.time()
        for seed in range(seeds):
            ident = identify.identify(model, [_log(kind, level, gs, scales, noise, 1000 + seed)])
            for k in truth:
                e = ident.estimate(k)
                est[k].append((e.estimate, e.std_error, e.interval_95) if e.identifiable else None)
        for k, v in truth.items():
            fits = [x for x in est[k] if x is not None]
            if not fits:
                rows.append({"robot": kind, "level": level, "parameter": k, "identifiable": 0, "fits": seeds})
                continue
            e = np.array([x[0] for x in fits])
            se = np.array([x[1] for x in fits])
            cover = np.mean([lo <= v <= hi for _, _, (lo, hi) in fits])
            z = (e - v) / se  # standard normal if the errors are what the standard errors say
            rows.append(
                {
                    "robot": kind,
                    "level": level,
                    "parameter": k,
                    "truth": v,
                    "fits": len(fits),
                    "identifiable": len(fits),
                    "coverage": float(cover),
                    "mean_estimate": float(e.mean()),
                    "mean_std_error": float(se.mean()),
                    "spread_of_estimates": float(e.std(ddof=1)),
                    "sd_of_z": float(z.std(ddof=1)),
                    "max_abs_z": float(np.abs(z).max()),
                }
            )
        print(f"{kind} {level}: {seeds} fits in {time.time() - t0:.0f} s", flush=True)
    return rows


def bootstrap(replicates: int) -> list:
    """Per robot, one log fitted, then ``replicates`` logs simulated (by SciPy) from the *fitted*
    parameters and noise with the same commands, each fitted: the replicates' spread against the
    first fit's standard errors (a parametric bootstrap)."""
    rows = []
    for kind, level, gs, scales, noise in CONFIGS:
        model = _model(kind, level)
        seed = 5000
        first = identify.identify(model, [_log(kind, level, gs, scales, noise, seed)])
        theta = first.theta()
        sigma = [e.estimate for e in first.noise_std]
        reps = []
        for b in range(replicates):
            log = _log(kind, level, theta[0], theta[1:], sigma, seed, noise_seed=b)
            reps.append(identify.identify(model, [log]))
        for e in first.parameters + first.noise_std:
            if not e.identifiable:
                continue
            boot = np.array([r.estimate(e.name).estimate for r in reps])
            rows.append(
                {
                    "robot": kind,
                    "level": level,
                    "parameter": e.name,
                    "hessian_std_error": e.std_error,
                    "bootstrap_sd": float(boot.std(ddof=1)),
                    "replicates": replicates,
                }
            )
    return rows


def time_one_fit() -> dict:
    """The fit of a 30 s, 50 Hz log of the shipped car, cold then warm (run in a fresh process)."""
    log = _log("(1,1)", "torque", 1.06, [0.92, 1.04], [0.01, 0.01, 0.005, 0.005], 100, n=1501)
    model = identify.sections.plant_model(Problem.load(ROOT / "wmrjax/examples/car_waypoints.toml").setting("identify"))
    t1 = time.time()
    ident = identify.identify(model, [log])
    t2 = time.time()
    identify.identify(model, [log._replace(posture=log.posture + 1e-4)])
    t3 = time.time()
    return {"cold_s": t2 - t1, "warm_s": t3 - t2, "iterations": ident.iterations, "converged": ident.converged}


def timing() -> dict:
    """:func:`time_one_fit` in a fresh process (this script with ``--time-one``), and that process's wall time."""
    env = dict(os.environ, JAX_PLATFORMS="cpu")
    t0 = time.time()
    out = subprocess.run(
        [sys.executable, "-m", "benchmarks.identify", "--time-one"],
        cwd=ROOT,
        env=env,
        capture_output=True,
        text=True,
        check=True,
    )
    return {**json.loads(out.stdout.strip().splitlines()[-1]), "process_s": time.time() - t0}


def table(rows) -> str:
    lines = [
        "| robot, level | parameter | truth | identifiable fits | coverage of the 95 % interval | mean std error | "
        "spread of estimates | sd of (estimate - truth) / std error | largest |",
        "|---|---|---|---|---|---|---|---|---|",
    ]
    for r in rows:
        if "coverage" not in r:
            lines.append(
                f"| {r['robot']} {r['level']} | {r['parameter']} | - | 0 of {r['fits']} (not identifiable) | - | - | - | - | - |"
            )
            continue
        lines.append(
            f"| {r['robot']} {r['level']} | {r['parameter']} | {r['truth']} | {r['fits']} | {r['coverage']:.0%} | "
            f"{r['mean_std_error']:.3g} | {r['spread_of_estimates']:.3g} | {r['sd_of_z']:.2f} | {r['max_abs_z']:.1f} |"
        )
    return "\n".join(lines)


def bootstrap_table(rows) -> str:
    lines = [
        "| robot, level | parameter | std error (Hessian) | sd over the bootstrap's fits | ratio |",
        "|---|---|---|---|---|",
    ]
    for r in rows:
        lines.append(
            f"| {r['robot']} {r['level']} | {r['parameter']} | {r['hessian_std_error']:.3g} | {r['bootstrap_sd']:.3g} | "
            f"{r['bootstrap_sd'] / r['hessian_std_error']:.2f} |"
        )
    return "\n".join(lines)


def main(argv=None) -> int:
    p = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    p.add_argument("--out", type=Path, default=ROOT / "results" / "benchmarks" / "identify")
    p.add_argument("--seeds", type=int, default=50)
    p.add_argument("--replicates", type=int, default=200, help="the parametric bootstrap's fits per robot")
    p.add_argument("--record", action="store_true", help="write the page's record (benchmarks/records/identify.json)")
    p.add_argument("--time-one", action="store_true", help=argparse.SUPPRESS)  # the timing's fresh process
    a = p.parse_args(argv)
    machine.configure_xla()  # before JAX starts its backend
    jax.config.update("jax_enable_x64", True)
    if a.time_one:
        print(json.dumps(time_one_fit()))
        return 0
    t = timing()
    print(
        f"30 s, 50 Hz (1,1) car log: fit cold {t['cold_s']:.1f} s, warm {t['warm_s']:.1f} s (process {t['process_s']:.1f} s)"
    )
    rows = coverage(a.seeds)
    print(table(rows))
    boot = bootstrap(a.replicates)
    print(bootstrap_table(boot))
    command = f"python -m benchmarks.identify --seeds {a.seeds} --replicates {a.replicates} --record"
    page.save(
        "identify", a.out, record_too=a.record, command=command, timing=t, coverage=rows, bootstrap=boot,
        seeds=a.seeds, replicates=a.replicates,
    )  # fmt: skip
    return 0


if __name__ == "__main__":
    sys.exit(main())
