r"""Side-by-side speed of the §6.1 closed-loop batch rollout (RK4, dt = 0.01, 1000 steps, float64).

Compares, in one run and on the same initial conditions: wmrjax (``batch_map``: one
device per core, 512-trajectory chunks, with and without the per-step error estimate of
``simulate``; and plain ``jit(vmap)`` on one device), a NumPy
implementation vectorised over the batch, SciPy ``solve_ivp`` one trajectory at a time,
and the hand-vectorised C loop ``benchmarks/bench/closed_loop_simd.c`` (the ceiling; skipped
with a note if no C compiler or source is found). Also times a reverse-mode gradient of a
batch tracking loss with respect to the gains relative to the forward pass.

    python -m benchmarks.benchmark --out results/benchmark [--batches 1024 16384 65536]

On a GPU (``--dtype float32`` for single precision): ``batch_map`` and
``batch_value_and_grad`` run one chunk per device there by default (their 512- and 256-example
chunks are for CPU caches), and ``--baseline-max-batch`` keeps the NumPy and C rows to the
batches a CPU finishes quickly; ``benchmarks/bench/gpu_benchmark.sh`` is the command the benchmarks page's GPU table ran.

Writes ``summary.json`` (trajectory-steps per second and ratios). No figure: numbers only.
"""

from __future__ import annotations

import argparse
import json
import math
import os
import platform
import re
import shutil
import subprocess
import sys
import tempfile
import time
from pathlib import Path

from paper import common
from wmrjax.cli import machine, running

N_STEPS = 1000
DT = 0.01
S2 = math.sqrt(2.0)
A62 = S2 * 1e-2 / 3


def initial_states_numpy(batch):
    """Same initial conditions as the C loop: x spread by +-5 cm around (63)."""
    import numpy as np

    b = np.arange(batch)
    p = A62 * 1000.0 + 5 * S2 / 6
    pd = -6 * A62 * 100.0 - S2 / 2
    return np.stack(
        [
            p - 0.54 + 0.1 * ((b % 97) / 97.0 - 0.5),
            np.full(batch, p + 0.54),
            np.full(batch, 3 * np.pi / 4),
            np.full(batch, S2 * (-pd)),
        ],
        axis=1,
    )


def numpy_rollout(S):
    """The §6.1 closed loop (eq 39 law) in NumPy, vectorised over the batch (S: (B, 4))."""
    import numpy as np

    x, y, th, c = (S[:, i].copy() for i in range(4))
    f = lambda t, *s: numpy_rollout_rhs(t, s)

    for i in range(N_STEPS):
        t = i * DT
        k1 = f(t, x, y, th, c)
        k2 = f(t + DT / 2, *(a + DT / 2 * k for a, k in zip((x, y, th, c), k1)))
        k3 = f(t + DT / 2, *(a + DT / 2 * k for a, k in zip((x, y, th, c), k2)))
        k4 = f(t + DT, *(a + DT * k for a, k in zip((x, y, th, c), k3)))
        x, y, th, c = (
            a + DT / 6 * (q1 + 2 * q2 + 2 * q3 + q4) for a, q1, q2, q3, q4 in zip((x, y, th, c), k1, k2, k3, k4)
        )
    return np.stack([x, y, th, c], axis=1)


def _best_time(fn, reps):
    best = math.inf
    out = None
    for _ in range(reps):
        t0 = time.perf_counter()
        out = fn()
        best = min(best, time.perf_counter() - t0)
    return best, out


def c_ceiling(batches, source: Path):
    """Build and run the SIMD C loop; returns {B: M traj-steps/s} or a note."""
    cc = shutil.which("gcc") or shutil.which("cc")
    if cc is None:
        return None, "no C compiler found: C ceiling skipped"
    if not source.exists():
        return None, f"{source} not found: C ceiling skipped"
    with tempfile.TemporaryDirectory() as tmp:
        exe = Path(tmp) / "simd"
        cmd = [cc, "-O3", "-march=native", "-ffast-math", "-fopenmp", str(source), "-lm", "-o", str(exe)]
        r = subprocess.run(cmd, capture_output=True, text=True)
        if r.returncode:
            return None, f"C build failed ({' '.join(cmd)}): {r.stderr.strip()[:300]}"
        res = {}
        for b in batches:
            best = 0.0
            for _ in range(3):
                o = subprocess.run([str(exe), str(b)], capture_output=True, text=True, check=True).stdout
                m = re.search(r"([0-9.]+) M traj-steps/s", o)
                best = max(best, float(m.group(1)))
            res[b] = best * 1e6
        return res, " ".join(cmd)


N_GROUPS = 16  # gradient_many: 16 groups x 4 pole parameters = 64 parameters


def section_6_1_per_example(ctrl, params, n_steps, groups=None):
    """Squared position error of one section 6.1 trajectory, ``f(poles, z0, i)``.

    ``poles`` (2, 2), or (groups, 2, 2) with trajectory ``i`` using group ``i mod groups``.
    """
    import jax
    import jax.numpy as jnp

    import wmrjax as w

    def one(poles, z, i):
        pl = poles if groups is None else poles[i % groups]
        p = params._replace(gains=w.Gains.from_poles(pl))
        tr = w.simulate(ctrl, z, p, dt=DT, n_steps=n_steps, save_every=10)
        e = jax.vmap(lambda t, s: ctrl.error(t, s, p)[0])(tr.t, tr.state)  # position errors
        return jnp.mean(jnp.sum(e**2, axis=-1))

    return one


def section_6_1_loss(ctrl, params, n_steps, groups=None, chunk: int | None = None):
    """Mean squared position error of the section 6.1 loop over a batch of initial states.

    ``loss(poles, z0s)``: the mean over the batch of :func:`section_6_1_per_example` (shared
    poles broadcast per example: each trajectory accumulates its own sensitivity and the batch
    is reduced once at the end).
    """
    import jax.numpy as jnp

    import wmrjax as w

    one = section_6_1_per_example(ctrl, params, n_steps, groups)

    def loss(poles, z0s):
        b = z0s.shape[0]
        pb = jnp.broadcast_to(poles, (b,) + poles.shape)
        return jnp.mean(w.batch_map(one, pb, z0s, jnp.arange(b), chunk=chunk))

    return loss


def section_6_1_batch_value_and_grad(ctrl, params, n_steps, groups=None, mode="auto", chunk: int | None = None):
    """``vg(poles, z0s) -> (loss, grad)`` of :func:`section_6_1_loss` by
    :func:`wmrjax.batch_value_and_grad` (per-example reverse mode above
    ``wmrjax.autodiff.BATCH_FORWARD_MAX_PARAMETERS`` = 1 parameter)."""
    import jax.numpy as jnp

    import wmrjax as w

    vg = w.batch_value_and_grad(section_6_1_per_example(ctrl, params, n_steps, groups), mode=mode, chunk=chunk)
    return lambda poles, z0s: vg(poles, z0s, jnp.arange(z0s.shape[0]))


def _best_times(fns: dict, reps: int, rounds: int):
    """Best wall time of each of ``fns`` (name -> thunk) and its last output, timed in ``rounds``
    alternating rounds of ``reps`` calls each: on a shared machine a slow spell then slows every
    function of a round, not the one that happened to be timed during it, so ratios hold."""
    best = {k: math.inf for k in fns}
    outs = {}
    for _ in range(rounds):
        for k, fn in fns.items():
            t, outs[k] = _best_time(fn, reps)
            best[k] = min(best[k], t)
    return best, outs


def gradient_ratios(loss, batch_vg, theta, z0s, reps, modes, compiled: dict, rounds: int = 3):
    """Forward time and value-and-gradient times of ``loss(theta, z0s)``, same run.

    The headline (``method``, ``mode``, ``value_and_grad_s``, ``ratio_grad_over_forward``) is
    ``batch_vg`` (:func:`wmrjax.batch_value_and_grad`, mode "auto"); each of ``modes`` is also
    timed with :func:`wmrjax.value_and_grad` on the batch mean (``ratio_<mode>_mode``, "auto"
    reported with the mode it resolved to). Every gradient is compared with the headline's.
    The forward pass and the gradients are timed alternately, ``rounds`` rounds of ``reps``
    calls each (best kept). ``compiled`` keeps the jitted functions per key, so that later
    batch sizes reuse them.
    """
    import jax
    import numpy as np

    import wmrjax as w

    n = int(np.size(theta))
    fwd = compiled.setdefault((loss, "value"), jax.jit(loss))
    bvg = compiled.setdefault((loss, "batch"), jax.jit(batch_vg))
    fns = {
        "forward": lambda: fwd(theta, z0s).block_until_ready(),
        "headline": lambda: jax.block_until_ready(bvg(theta, z0s)),
    }
    keys = {}
    for mode in modes:
        resolved = w.autodiff.choose_mode(n, mode)
        vg = compiled.setdefault((loss, resolved), jax.jit(w.value_and_grad(loss, mode=resolved)))
        keys[mode] = f"value_and_grad_{mode}" + (f"_{resolved}" if mode == "auto" else "")
        fns[keys[mode]] = lambda vg=vg: jax.block_until_ready(vg(theta, z0s))
    for fn in fns.values():  # compile (and warm) everything before timing anything
        fn()
    best, outs = _best_times(fns, reps, rounds)
    tf, val = best["forward"], outs["forward"]
    out = {"n_parameters": n, "forward_s": tf, "loss_value": float(val)}
    tg, (v, g_head) = best["headline"], outs["headline"]
    g_head = np.asarray(g_head)
    out.update(
        method="wmrjax.batch_value_and_grad",
        mode=w.autodiff.choose_mode(n, "auto", w.autodiff.BATCH_FORWARD_MAX_PARAMETERS),
        value_and_grad_s=tg,
        ratio_grad_over_forward=tg / tf,
        grad_finite=bool(np.all(np.isfinite(g_head))),
        abs_diff_value_vs_forward_pass=abs(float(v) - float(val)),
    )
    diffs = {}
    for key in keys.values():
        out[f"{key}_mode_s"] = best[key]
        out[f"ratio_{key}_mode"] = best[key] / tf
        diffs[key] = float(np.max(np.abs(np.asarray(outs[key][1]) - g_head)))
    if diffs:
        out["max_abs_diff_vs_headline_gradient"] = diffs
    return out


def run(
    out: Path,
    batches,
    reps: int,
    grad_batch: int,
    grad_batches,
    scipy_trajs: int,
    source: Path,
    many_forward: bool = True,
    dtype: str = "float64",
    chunk: int | None = None,
    baseline_max_batch: int | None = None,
) -> dict:
    if dtype == "float64":
        common.enable_x64()
    import jax

    ctrl, params, _, _ = common.section_6_1_setup()
    baselines = [b for b in batches if baseline_max_batch is None or b <= baseline_max_batch]
    rows, c_note = _rollout_rows(ctrl, params, batches, reps, source, chunk, baselines)
    scipy_rate, nfev = _scipy_rate(scipy_trajs)
    gradient, gradient_many, by_batch = _gradients(ctrl, params, reps, grad_batch, grad_batches, many_forward, chunk)
    summary = {
        "experiment": "benchmark",
        "closed_loop": "section 6.1: (2,0) robot, e = 0, dynamic FL (eq 39), poles -1, reference (62)",
        "integration": {"method": "RK4", "dt": DT, "steps": N_STEPS, "dtype": dtype},
        "batch_map_chunk": chunk
        if chunk is not None
        else "the library's default (512 on CPUs, 256 for "
        "per-example reverse mode; one chunk per device on accelerators)",
        "baselines": "NumPy, C and SciPy compute in float64 whatever the dtype; NumPy and C rows for batches "
        + ("of every size" if baseline_max_batch is None else f"up to {baseline_max_batch} trajectories"),
        "machine": {
            "cpu_count": os.cpu_count(),
            "jax_devices": len(jax.devices()),
            "platform": platform.platform(),
            "jax_version": jax.__version__,
            "backend": jax.default_backend(),
            "device_kind": jax.devices()[0].device_kind,
        },
        "units": "trajectory-steps per second (batch size x 1000 steps / wall time, best of reps, compile excluded)",
        "gradient_timing": "seconds, best of reps x rounds: the forward pass and the gradients timed alternately, "
        "reps calls each per round (3 rounds; gradient_by_batch above 10000 trajectories: "
        "2 rounds of reps // 2 calls)",
        "rollout": rows,
        "c_ceiling_note": c_note,
        "scipy_solve_ivp_one_at_a_time": {
            "method": "RK45",
            "rtol": 1e-8,
            "atol": 1e-10,
            "trajectories": scipy_trajs,
            "mean_rhs_evaluations": nfev / scipy_trajs,
            "equivalent_traj_steps_per_s": scipy_rate,
        },
        "gradient": gradient,
        "gradient_many": gradient_many,
        "gradient_by_batch": by_batch,
    }
    for b, row in rows.items():
        row["ratio_wmrjax_over_scipy"] = row["wmrjax_batch_map"] / scipy_rate
        row["ratio_jit_vmap_1_device_over_scipy"] = row["wmrjax_jit_vmap_1_device"] / scipy_rate
    common.write_json(out / "summary.json", summary)
    return summary


def _rollout_rows(ctrl, params, batches, reps: int, source: Path, chunk: int | None = None, baselines=None):
    """Per batch size: trajectory-steps per second of wmrjax (batch_map in chunks of ``chunk`` with
    and without the error estimate, jit(vmap) on one device), vectorised NumPy and the C ceiling
    (for the ``baselines`` batch sizes, default all), with their ratios; ``(rows, the C ceiling's
    note)``."""
    import jax
    import jax.numpy as jnp
    import numpy as np

    import wmrjax as w

    sim_final = lambda z: w.simulate(ctrl, z, params, dt=DT, n_steps=N_STEPS, save_every=N_STEPS).final_state
    baselines = list(batches) if baselines is None else list(baselines)
    fast = jax.jit(lambda z: w.batch_map(sim_final, z, chunk=chunk))
    # the same loop without the per-step error estimate (error_tol=None): what the guard costs
    sim_bare = lambda z: (
        w.simulate(ctrl, z, params, dt=DT, n_steps=N_STEPS, save_every=N_STEPS, error_tol=None).final_state
    )
    bare = jax.jit(lambda z: w.batch_map(sim_bare, z, chunk=chunk))
    plain = jax.jit(jax.vmap(sim_final))
    rows = {}
    c_res, c_note = c_ceiling(baselines, source) if baselines else (None, "no batch within --baseline-max-batch")
    for b in batches:
        S = initial_states_numpy(b)
        Z = jnp.asarray(S)
        row = {}
        t_compile0 = time.perf_counter()
        fast(Z).block_until_ready()
        row["wmrjax_compile_s"] = time.perf_counter() - t_compile0
        t, zf = _best_time(lambda: fast(Z).block_until_ready(), reps)
        row["wmrjax_batch_map"] = b * N_STEPS / t
        bare(Z).block_until_ready()
        tb, zb = _best_time(lambda: bare(Z).block_until_ready(), reps)
        row["wmrjax_batch_map_no_error_estimate"] = b * N_STEPS / tb
        row["max_abs_diff_with_vs_without_error_estimate"] = float(np.max(np.abs(np.asarray(zf) - np.asarray(zb))))
        plain(jax.device_put(Z, jax.devices()[0])).block_until_ready()
        t1, _ = _best_time(lambda: plain(Z).block_until_ready(), reps)
        row["wmrjax_jit_vmap_1_device"] = b * N_STEPS / t1
        if b in baselines:
            tn, zn = _best_time(lambda: numpy_rollout(S), 1 if b > 20000 else 2)
            row["numpy_vectorised"] = b * N_STEPS / tn
            row["max_abs_diff_wmrjax_vs_numpy"] = float(np.max(np.abs(np.asarray(zf) - zn)))
        if c_res and b in c_res:
            row["c_simd_ceiling"] = c_res[b]
            row["ratio_wmrjax_over_c"] = row["wmrjax_batch_map"] / c_res[b]
            row["ratio_wmrjax_no_error_estimate_over_c"] = row["wmrjax_batch_map_no_error_estimate"] / c_res[b]
            row["ratio_numpy_over_c"] = row["numpy_vectorised"] / c_res[b]
            row["ratio_jit_vmap_1_device_over_c"] = row["wmrjax_jit_vmap_1_device"] / c_res[b]
        rows[str(b)] = row
        print(
            f"B={b}: wmrjax {row['wmrjax_batch_map'] / 1e6:.2f} M/s (without the error estimate "
            f"{row['wmrjax_batch_map_no_error_estimate'] / 1e6:.2f}; jit(vmap) 1 device "
            f"{row['wmrjax_jit_vmap_1_device'] / 1e6:.2f})"
            + (f", numpy {row['numpy_vectorised'] / 1e6:.2f}" if "numpy_vectorised" in row else "")
            + (
                f", C {c_res[b] / 1e6:.2f} -> ratio {row['ratio_wmrjax_over_c']:.2f}" if "c_simd_ceiling" in row else ""
            ),
            flush=True,
        )

    return rows, c_note


# sampling rates of the reference-family rows: the §6.1 reference sampled, then interpolated
REFERENCE_RATES_HZ = (10, 100)


def _reference_cases(level: str):
    """The §6.1 loop at ``level`` with its built-in reference (62) and the same path sampled at
    :data:`REFERENCE_RATES_HZ` over the horizon: ``(ctrl, {name: params}, z0s_of(batch))``."""
    import jax
    import jax.numpy as jnp
    import numpy as np

    import wmrjax as w
    from wmrjax import references

    ctrl = w.dynamic_linearization("(2,0)", level)
    builtin = references.paper_62()
    params = ctrl.params(builtin, poles=1.0, geometry=w.Geometry(e=0.0))
    cases = {"builtin": params}
    for rate in REFERENCE_RATES_HZ:
        ts = np.linspace(0.0, N_STEPS * DT, int(round(N_STEPS * DT * rate)) + 1)
        xy = np.asarray(jax.vmap(builtin.position)(jnp.asarray(ts)))
        cases[f"samples_{rate}hz"] = params._replace(reference=references.from_samples(ts, xy))
    z_ref = ctrl.reference_state(0.0, params)
    spread = np.zeros(z_ref.shape[0])
    spread[0] = 1.0  # x spread by +-5 cm around the reference, as the rollout rows

    def z0s_of(batch):
        b = np.arange(batch)
        return jnp.asarray(np.asarray(z_ref) + 0.1 * ((b % 97) / 97.0 - 0.5)[:, None] * spread)

    return ctrl, cases, z0s_of


def reference_rows(batch: int, reps: int, levels=None) -> dict:
    """Per level: compile time and run time of a ``jit(vmap)`` batch rollout of the §6.1 loop with
    the built-in reference and with the same path sampled (quintic spline), side by side, and
    their ratios to the built-in one (``levels``: :class:`wmrjax.Level` values, default both).
    Compile time: each case's first call beyond its second, from empty caches (``jax.clear_caches``)."""
    import jax
    import numpy as np

    import wmrjax as w
    from wmrjax import Level

    out = {}
    for level in list(Level) if levels is None else [Level(x) for x in levels]:
        ctrl, cases, z0s_of = _reference_cases(level)
        z0s = z0s_of(batch)
        fns = {
            name: jax.jit(jax.vmap(lambda z, p=p: w.simulate(ctrl, z, p, dt=DT, n_steps=N_STEPS, save_every=N_STEPS)))
            for name, p in cases.items()
        }
        compile_s = {}
        for name, fn in fns.items():
            # every case's first call from empty caches: the sections before this one compiled the
            # built-in reference's check over the horizon and the small programs the cases share,
            # which the first case then skipped and the others paid
            jax.clear_caches()
            compile_s[name] = _first_call(fn, z0s)
        for fn in fns.values():  # compiled again where the caches were cleared, outside the timing
            jax.block_until_ready(fn(z0s))
        # run times in alternating rounds: a slow spell of the machine slows every case alike
        best, trs = _best_times({n: (lambda fn=fn: jax.block_until_ready(fn(z0s))) for n, fn in fns.items()}, reps, 3)
        rows = {}
        for name in fns:
            final = np.asarray(trs[name].final_state)
            rows[name] = {
                "compile_s": compile_s[name],
                "run_s": best[name],
                "traj_steps_per_s": batch * N_STEPS / best[name],
                "run_over_builtin": best[name] / best["builtin"],
                "compile_over_builtin": compile_s[name] / compile_s["builtin"],
                "max_abs_diff_final_state_vs_builtin": float(
                    np.max(np.abs(final - np.asarray(trs["builtin"].final_state)))
                ),
                "failed": int(np.sum(np.asarray(trs[name].diagnostics.failed))),
            }
        out[str(level)] = rows
        print(
            f"references ({level}, B={batch}): "
            + ", ".join(
                f"{n} run {r['run_over_builtin']:.2f}x compile {r['compile_over_builtin']:.2f}x"
                for n, r in rows.items()
            ),
            flush=True,
        )
    return out


# the exported control step's rows: controller period [s] and RK4 steps of the plant per period
EXPORT_PERIOD = 0.01
EXPORT_STEPS_PER_PERIOD = 5


def _example_setup(case: str):
    """``(ctrl, params, z0)`` of a ``family/type/level`` case: the table row's example set-up on a
    circle (as the compile-time rows), started near the reference."""
    import jax.numpy as jnp

    import wmrjax as w
    from wmrjax import references
    from wmrjax.controllers import place

    family, kind, level = case.split("/")
    ctrl = (w.dynamic_linearization if family == "dynamic" else w.static_linearization)(kind, level)
    offset = getattr(ctrl.row, "default_heading_offset", 0.0)
    ref = references.circle(radius=2.0, omega=0.4, heading_offset=offset)
    params = ctrl.params(ref, poles=1.5, geometry=ctrl.row.default_geometry)
    if family == "dynamic":
        z = ctrl.reference_state(0.0, params).at[0].add(0.05)
    else:  # the problems' placement: 5 cm off in x, on the reference otherwise
        error = jnp.zeros(ctrl.robot.n_state).at[0].set(0.05)
        z = place(ctrl, params, error, "physical", ctrl.task, 1.0)
    return ctrl, params, z


def _c_flags():
    from wmrjax.export.check import C_FLAGS

    return C_FLAGS


def export_rows(n_samples: int, cc: str | None, cases=None) -> dict:
    """Per ``family/type/level``: the exported control step checked over a closed-loop run of
    ``n_samples`` periods (:func:`wmrjax.cli.export.verify`: JAX step vs the simulator, the C and
    the reloaded artifact vs the JAX step) and the C step's time per call."""
    import tempfile

    from wmrjax import export as X
    from wmrjax.export import check as E

    rows = {}
    for case in cases or _compile_cases():
        ctrl, params, z0 = _example_setup(case)
        step = X.control_step(ctrl, params)
        with tempfile.TemporaryDirectory() as d:
            E.write_export(step, Path(d))
            run = X.reference_run(
                step,
                ctrl,
                params,
                z0,
                period=EXPORT_PERIOD,
                n_samples=n_samples,
                steps_per_sample=EXPORT_STEPS_PER_PERIOD,
            )
            row = E.verify(step, run, period=EXPORT_PERIOD, directory=Path(d), cc=cc)
            row["c_lines"] = (Path(d) / f"{step.name}.c").read_text().count("\n")
        rows[case] = row
        ns = f"{row['c_seconds_per_step'] * 1e9:.0f} ns" if "c_seconds_per_step" in row else "no C"
        print(
            f"export {case}: {ns}, C vs JAX {row.get('c_vs_jax', float('nan')):.1e}, artifact {row['artifact_vs_jax']:.1e}, "
            f"JAX vs simulator {row['jax_vs_simulator']:.1e} ({row['samples']} periods{'' if row['run_complete'] else ', cut at a failure'})",
            flush=True,
        )
    return rows


def _scipy_rate(scipy_trajs: int):
    """``(equivalent trajectory-steps per second, right-hand-side evaluations)`` of SciPy."""
    import numpy as np
    from scipy.integrate import solve_ivp

    # SciPy, one trajectory at a time: adaptive RK45 (rtol 1e-8, atol 1e-10) on the same
    # closed loop; reported as equivalent trajectory-steps/s (1000 steps per trajectory).
    S = initial_states_numpy(scipy_trajs)

    def rhs(t, s):
        return np.array(numpy_rollout_rhs(t, s))

    t0 = time.perf_counter()
    nfev = 0
    for i in range(scipy_trajs):
        sol = solve_ivp(rhs, (0.0, N_STEPS * DT), S[i], method="RK45", rtol=1e-8, atol=1e-10)
        nfev += sol.nfev
    ts = time.perf_counter() - t0
    return scipy_trajs * N_STEPS / ts, nfev


def _gradients(ctrl, params, reps: int, grad_batch: int, grad_batches, many_forward: bool, chunk: int | None = None):
    """The gradient timings: 4 shared poles, per-group poles, and by batch size; ``(gradient,
    gradient_many, gradient_by_batch)``."""
    import jax.numpy as jnp

    # Gradients: value and gradient of a batch tracking loss relative to its forward pass
    zg = jnp.asarray(initial_states_numpy(grad_batch))
    loss = section_6_1_loss(ctrl, params, N_STEPS, chunk=chunk)
    loss_vg = section_6_1_batch_value_and_grad(ctrl, params, N_STEPS, chunk=chunk)
    poles = jnp.ones((2, 2))
    compiled = {}
    gradient = gradient_ratios(loss, loss_vg, poles, zg, reps, ("forward", "reverse"), compiled)
    gradient.update(
        batch=grad_batch,
        loss="mean squared position error, saved every 10 steps",
        parameters="real closed-loop poles (2 outputs x 2), shared by the batch",
    )
    print(
        f"gradient (B = {grad_batch}, {gradient['n_parameters']} parameters): "
        f"{gradient['ratio_grad_over_forward']:.2f}x forward (batch_value_and_grad, {gradient['mode']}); "
        f"value_and_grad forward {gradient['ratio_value_and_grad_forward_mode']:.2f}x, "
        f"reverse {gradient['ratio_value_and_grad_reverse_mode']:.2f}x",
        flush=True,
    )
    many_poles = jnp.ones((N_GROUPS, 2, 2))
    gradient_many = gradient_ratios(
        section_6_1_loss(ctrl, params, N_STEPS, groups=N_GROUPS, chunk=chunk),
        section_6_1_batch_value_and_grad(ctrl, params, N_STEPS, groups=N_GROUPS, chunk=chunk),
        many_poles,
        zg,
        reps,
        ("auto", "forward") if many_forward else ("auto",),
        compiled,
    )
    gradient_many.update(batch=grad_batch, parameters=f"per-group poles: {N_GROUPS} groups of trajectories x 2 x 2")
    print(
        f"gradient_many ({gradient_many['n_parameters']} parameters): {gradient_many['ratio_grad_over_forward']:.2f}x "
        f"(batch_value_and_grad, {gradient_many['mode']}); value_and_grad "
        f"{gradient_many['ratio_value_and_grad_auto_reverse_mode']:.2f}x (reverse)"
        + (
            f", forward sensitivities {gradient_many['ratio_value_and_grad_forward_mode']:.2f}x" if many_forward else ""
        ),
        flush=True,
    )
    by_batch = {}
    for b in grad_batches:
        r = gradient_ratios(
            loss,
            loss_vg,
            poles,
            jnp.asarray(initial_states_numpy(b)),
            max(1, reps // 2 if b > 10000 else reps),
            ("forward",),
            compiled,
            rounds=2 if b > 10000 else 3,
        )
        # beside it, forward sensitivities through the batched loop (the memory of a forward pass)
        by_batch[str(b)] = {
            k: r[k]
            for k in (
                "method",
                "mode",
                "forward_s",
                "value_and_grad_s",
                "ratio_grad_over_forward",
                "value_and_grad_forward_mode_s",
                "ratio_value_and_grad_forward_mode",
            )
        }
        print(
            f"gradient_by_batch B = {b}: {r['ratio_grad_over_forward']:.2f}x (batch_value_and_grad, {r['mode']}); "
            f"value_and_grad {r['ratio_value_and_grad_forward_mode']:.2f}x (forward)",
            flush=True,
        )

    return gradient, gradient_many, by_batch


def numpy_rollout_rhs(t, s):
    """Right-hand side of the §6.1 closed loop for one state (used with solve_ivp)."""
    import numpy as np

    x, y, th, c = s
    u = 10 - 2 * t
    p = A62 * u**3 - S2 / 2 * t + 5 * S2 / 6
    pd = -6 * A62 * u**2 - S2 / 2
    pdd = 24 * A62 * u
    sn, cs = np.sin(th), np.cos(th)
    hd1, hd2 = -c * sn, c * cs
    w1 = pdd - 2 * (hd1 - pd) - (x - p)
    w2 = pdd - 2 * (hd2 - pd) - (y - p)
    return hd1, hd2, (-cs * w1 - sn * w2) / c, -sn * w1 + cs * w2


def _compile_cases():
    """Every row of Tables 4 (dynamic) and 3 (static) at both levels, as 'family/type/level'."""
    from wmrjax.controllers import TABLE3, TABLE4, Level

    return [
        f"{family}/{kind}/{level}"
        for family, table in (("dynamic", TABLE4), ("static", TABLE3))
        for kind in table
        for level in Level
    ]


def _first_call(fn, *args):
    """Seconds of a first call beyond a second one (tracing and compilation)."""
    import jax

    t0 = time.perf_counter()
    jax.block_until_ready(fn(*args))
    t1 = time.perf_counter()
    jax.block_until_ready(fn(*args))
    return max(0.0, 2 * t1 - t0 - time.perf_counter())


def compile_worker(case: str, batch: int) -> dict:
    """First-call compile times of a rollout loss and of its value and gradient (run in a fresh process).

    ``case``: ``"section_6_1"`` (the gradient block's loss) or ``"family/type/level"``.
    """
    common.enable_x64()
    import jax
    import jax.numpy as jnp
    import numpy as np

    import wmrjax as w
    from wmrjax import references

    if case == "section_6_1":
        ctrl, params, _, _ = common.section_6_1_setup()
        loss, theta = section_6_1_loss(ctrl, params, N_STEPS), jnp.ones((2, 2))
        vg = section_6_1_batch_value_and_grad(ctrl, params, N_STEPS)  # the gradient block's path
        mode = w.autodiff.choose_mode(int(np.size(theta)), "auto", w.autodiff.BATCH_FORWARD_MAX_PARAMETERS)
        z0s = jnp.asarray(initial_states_numpy(batch))
    else:
        family, kind, level = case.split("/")
        ctrl = (w.dynamic_linearization if family == "dynamic" else w.static_linearization)(kind, level)
        offset = getattr(ctrl.row, "default_heading_offset", 0.0)  # the table row's example set-up
        ref = references.circle(radius=2.0, omega=0.4, heading_offset=offset)
        params = ctrl.params(ref, poles=1.5, geometry=ctrl.row.default_geometry)
        if family == "dynamic":
            z = ctrl.reference_state(0.0, params)
        else:
            X = jnp.zeros(ctrl.robot.n_state).at[0].set(0.3).at[1].set(-0.2).at[3:].set(0.6)
            z = ctrl.initial_state_from_physical(X, jnp.full(ctrl.robot.n_input, 0.4), params)
        z0s = z + 0.01 * jnp.asarray(np.random.default_rng(0).normal(size=(batch, z.size)))
        theta = params.gains.coeffs

        def loss(coeffs, z0s):
            p = params._replace(gains=w.Gains(coeffs))
            tr = jax.vmap(lambda z: w.simulate(ctrl, z, p, dt=0.01, n_steps=N_STEPS, save_every=10))(z0s)
            e = jax.vmap(jax.vmap(lambda t, s: ctrl.error(t, s, p)[0]))(tr.t, tr.state)
            return jnp.mean(e**2)

        vg, mode = w.value_and_grad(loss), w.autodiff.choose_mode(int(np.size(theta)))
    out = {"n_parameters": int(np.size(theta)), "mode": mode}
    out["forward_s"] = _first_call(jax.jit(loss), theta, z0s)
    out["gradient_s"] = _first_call(jax.jit(vg), theta, z0s)
    return out


def memory_worker(n_steps: int, batch: int) -> dict:
    """Peak resident memory of the section 6.1 loss's value and gradient (run in a fresh process)."""
    import resource

    common.enable_x64()
    import jax
    import jax.numpy as jnp

    import wmrjax as w

    ctrl, params, _, _ = common.section_6_1_setup()
    vg = section_6_1_batch_value_and_grad(ctrl, params, n_steps)  # the gradient block's path
    poles = jnp.ones((2, 2))
    t0 = time.perf_counter()
    v, g = jax.block_until_ready(jax.jit(vg)(poles, jnp.asarray(initial_states_numpy(batch))))
    peak = resource.getrusage(resource.RUSAGE_SELF).ru_maxrss * 1024  # Linux: kilobytes
    return {
        "steps": n_steps,
        "batch": batch,
        "method": "wmrjax.batch_value_and_grad",
        "mode": w.autodiff.choose_mode(4, "auto", w.autodiff.BATCH_FORWARD_MAX_PARAMETERS),
        "peak_rss_bytes": int(peak),
        "peak_rss_gb": peak / 1e9,
        "wall_s": time.perf_counter() - t0,
        "loss_value": float(v),
        "grad_finite": bool(jnp.all(jnp.isfinite(g))),
    }


def _worker(args: list, env: dict) -> dict:
    import json

    r = subprocess.run(
        [sys.executable, "-m", "benchmarks.benchmark", *args],
        capture_output=True,
        text=True,
        env=env,
        cwd=Path(__file__).resolve().parent.parent,
    )
    if r.returncode:
        raise RuntimeError(f"benchmark worker {args} failed: {r.stderr[-2000:]}")
    return json.loads(r.stdout.strip().splitlines()[-1])


def compile_table(cases, batch: int, devices: int, progress=print) -> dict:
    """Compile times per case in fresh processes: first call with an empty persistent cache, then
    a second process reading the cache the first one wrote."""
    from wmrjax.xla_cpu import cpu_flags

    env = dict(os.environ)
    env["XLA_FLAGS"] = cpu_flags("", devices)  # the command lines' settings, nothing inherited
    out = {}
    with tempfile.TemporaryDirectory() as cache:
        for case in cases:
            first = _worker(
                ["--worker", "compile", "--case", case, "--worker-batch", str(batch), "--no-compile-cache"], env
            )
            _worker(
                ["--worker", "compile", "--case", case, "--worker-batch", str(batch), "--compile-cache", cache], env
            )
            cached = _worker(
                ["--worker", "compile", "--case", case, "--worker-batch", str(batch), "--compile-cache", cache], env
            )
            out[case] = dict(first, forward_cached_s=cached["forward_s"], gradient_cached_s=cached["gradient_s"])
            progress(
                f"compile {case}: rollout {first['forward_s']:.1f} s, gradient {first['gradient_s']:.1f} s "
                f"({first['mode']}); cached {cached['forward_s']:.2f} s / {cached['gradient_s']:.2f} s",
                flush=True,
            )
    return out


WORKERS_FILE = Path(__file__).resolve().parent / "workers.py"  # fresh-process measurements, run by path


def run_worker(tree: Path, *args, env: dict | None = None) -> dict:
    """``benchmarks/workers.py ARGS`` in a fresh process with ``tree``'s wmrjax first on the path
    (the worker file is this checkout's): its JSON line."""
    env = dict(os.environ if env is None else env)
    env["PYTHONPATH"] = os.pathsep.join([str(tree)] + ([env["PYTHONPATH"]] if env.get("PYTHONPATH") else []))
    r = subprocess.run(
        [sys.executable, str(WORKERS_FILE), *map(str, args)],
        capture_output=True,
        text=True,
        env=env,
        cwd=tree,
        timeout=1200,
    )
    if r.returncode:
        raise RuntimeError(f"worker {args} in {tree} failed:\n{r.stderr[-3000:]}")
    return json.loads(r.stdout.strip().splitlines()[-1])


def tuner_times(problems, baseline: Path | None, rounds: int = 3, progress=print) -> dict:
    """The tuner's gradient program (trace, compile, step) per problem, in fresh processes with no
    persistent cache (:func:`workers.tuner`), this checkout and ``baseline`` (another checkout
    with problem files' tuning, #31 or later) alternately, ``rounds`` times; the best of each is kept."""
    trees = {"this": Path(__file__).resolve().parent.parent} | ({"baseline": baseline.resolve()} if baseline else {})
    best = {}
    for r in range(rounds):
        for name in problems:
            for label, tree in trees.items():
                env = dict(os.environ, JAX_ENABLE_COMPILATION_CACHE="false")
                res = run_worker(tree, "tuner", name, env=env)
                key = (name, label)
                best[key] = (
                    res
                    if key not in best
                    else {k: (min(v, res[k]) if k.endswith("_s") else v) for k, v in best[key].items()}
                )
                progress(
                    f"tuner {name} ({label}, round {r + 1}): trace {res['trace_s']:.2f} s, compile "
                    f"{res['compile_s']:.2f} s, step {1e3 * res['step_s']:.1f} ms",
                    flush=True,
                )
    out = {
        "what": "the tuning loop's gradient program (wmrjax.tune.loop._gradient_step; benchmarks/workers.py tuner) on the problem's training set, "
        "in a fresh process with no persistent cache: trace, XLA compile, and the step (best of 3 x 5 "
        f"calls); best of {rounds} rounds, the checkouts alternating",
        "baseline": str(baseline) if baseline else None,
    }
    for name in problems:
        out[name] = {label: best[(name, label)] for label in trees}
        if baseline:
            a, b = best[(name, "this")], best[(name, "baseline")]
            out[name]["ratio_this_over_baseline"] = {k: a[k] / b[k] for k in ("trace_s", "compile_s", "step_s")}
    return out


# --- the memory model against measured peaks ------------------------------------------------
# The predicted memory of wmrjax.simulate, a tuning step and a sweep block, each measured in a
# fresh process as the growth of the peak resident memory (VmHWM) over a warm baseline, must lie
# above the measured peak and within resources.ESTIMATE_FACTOR of it (GRADIENT_ESTIMATE_FACTOR for
# the tuning step): measurements at scale (10^5 to 10^6 steps, 2048 scenarios), the benchmark's;
# the test suite checks the refusals the model drives (tests/test_resources.py).

# (name, worker, arguments) of benchmarks/workers.py: the reference check dominates the first
# simulate, the saved samples the second
CASES = (
    ("simulate_500000_steps_dt_0.02", "simulate", (500_000, 0.02)),
    ("simulate_2000000_steps_dt_1e-4", "simulate", (2_000_000, 1e-4)),
    ("tuning_step_64_to_2048_scenarios", "tune", ()),
    ("sweep_block_256_runs_10000_steps", "sweep", ()),
)
SWEEP_FILE = Path(__file__).resolve().parent / "bench" / "memory_sweep.toml"


def measure(worker: str, *args) -> dict:
    """A memory worker of :mod:`workers` in a fresh process: its ``{"measured", "predicted", ...}``."""
    return run_worker(Path(__file__).resolve().parents[1], worker, *args)


def memory_estimates(progress=print) -> dict:
    """Every case of :data:`CASES`: measured and predicted bytes, their ratio, and whether the
    prediction bounds the peak within its factor."""
    from wmrjax import resources

    rows = {}
    for name, key, args in CASES:
        if key == "sweep":
            with tempfile.TemporaryDirectory() as d:
                m = measure(key, SWEEP_FILE, Path(d) / "out")
        else:
            m = measure(key, *args)
        factor = resources.GRADIENT_ESTIMATE_FACTOR if key == "tune" else resources.ESTIMATE_FACTOR
        m["ratio"] = m["predicted"] / m["measured"]
        m["factor"] = factor
        m["within"] = bool(m["measured"] <= m["predicted"] <= factor * m["measured"])
        rows[name] = m
        progress(
            f"memory {name}: predicted {m['predicted'] / 1e6:.1f} MB, measured {m['measured'] / 1e6:.1f} MB, "
            f"ratio {m['ratio']:.2f} ({'within' if m['within'] else 'OUTSIDE'} [1, {factor}])"
        )
    return rows


# --- cold starts: every default job in a fresh process, empty compilation cache (#36) ----------

_S_PATH = "wmrjax/examples/s_path.toml"


TUNING_EXAMPLES = ("car_schedule", "section_6_1_plant", "torque_2_1")  # the shipped problems with [tune]
SWEEP_EXAMPLES = ("random_references", "sampled_lane_change", "section_6_1_position_grid")  # the shipped sweeps


def cold_start_jobs() -> dict:
    """The default jobs a user starts, by name: ``python -m`` arguments before ``--out``."""
    jobs = {"section_6_1": ["paper.section_6_1"], "section_6_2": ["paper.section_6_2"]}
    from wmrjax.controllers import TABLE4  # the types with a dynamic linearizing law: certify's

    for t in sorted(TABLE4):
        jobs[f"certify_{t}_figure_eight"] = ["wmrjax", "certify", "--robot", t, "--reference", "figure_eight"]
    for name in TUNING_EXAMPLES:
        jobs[f"tuning_{name}"] = ["wmrjax", "tune", name]
    for name in SWEEP_EXAMPLES:
        jobs[f"sweep_{name}"] = ["wmrjax", "sweep", name]
    for job, cmd in (("sweep", "sweep"), ("tuning", "tune"), ("certify", "certify")):
        jobs[f"s_path_{job}"] = ["wmrjax", cmd, _S_PATH]
    return jobs


def _timed_job(argv: list, out: Path, cache: Path) -> dict:
    """One run of ``python -m ARGV --out OUT --compile-cache CACHE`` from the repository root."""
    root = Path(__file__).resolve().parent.parent
    t0 = time.perf_counter()
    r = subprocess.run(
        [sys.executable, "-m", *argv, "--out", str(out), "--compile-cache", str(cache)],
        cwd=root,
        env=dict(os.environ, PYTHONPATH=str(root)),
        capture_output=True,
        text=True,
    )
    row = {"wall_s": round(time.perf_counter() - t0, 2), "exit": r.returncode}
    if r.returncode:
        row["stderr_tail"] = r.stderr[-500:]
    return row


def cold_start_rows(jobs: dict, progress=print) -> dict:
    """Per job: wall time in a fresh process with an empty persistent compilation cache (cold),
    then again reading the cache that run wrote (warm), and the compile share ``1 - warm / cold``
    (what a second start saves: compiling, not computing; tracing is in both)."""
    rows = {}
    for name, argv in jobs.items():
        with tempfile.TemporaryDirectory() as d:
            cold = _timed_job(argv, Path(d) / "cold", Path(d) / "cache")
            warm = _timed_job(argv, Path(d) / "warm", Path(d) / "cache")
        row = {"command": "python -m " + " ".join(argv), "cold_s": cold["wall_s"], "warm_s": warm["wall_s"]}
        row["compile_share"] = round(1.0 - warm["wall_s"] / cold["wall_s"], 3) if cold["wall_s"] > 0 else None
        row["exit"] = max(cold["exit"], warm["exit"])
        if "stderr_tail" in cold or "stderr_tail" in warm:
            row["stderr_tail"] = cold.get("stderr_tail") or warm.get("stderr_tail")
        rows[name] = row
        progress(
            f"cold start {name}: {row['cold_s']:.1f} s cold, {row['warm_s']:.1f} s warm "
            f"(compile share {row['compile_share']}), exit {row['exit']}"
        )
    return rows


def _parser():
    """The command's options (the workers' hidden ones included)."""
    from wmrjax.cli import options

    p = options.parser(__doc__.splitlines()[0], "results/benchmark", compile_cache=False)  # it times compilation
    p.add_argument(
        "--batches",
        type=options.count,
        nargs="+",
        default=[1024, 16384, 65536],
        help="batch sizes of the rollout comparison [trajectories]",
    )
    p.add_argument("--reps", type=options.count, default=5, help="timed repetitions (best kept)")
    _device_options(p)
    p.add_argument("--grad-batch", type=options.count, default=1024, help="batch of the gradient timing [trajectories]")
    p.add_argument(
        "--grad-batches",
        type=options.count,
        nargs="*",
        default=[1024, 8192, 65536],
        help="batches of gradient_by_batch [trajectories]",
    )
    p.add_argument(
        "--compile-types",
        choices=("all", "section_6_1", "none"),
        default="all",
        help="compile times in fresh processes: the section 6.1 loss and every type x level (several "
        "minutes), the section 6.1 loss only, or none",
    )
    p.add_argument(
        "--memory-steps", type=options.count, default=20000, help="horizon of the gradient memory measurement"
    )
    p.add_argument(
        "--memory-batch", type=int, default=4096, help="trajectories of the gradient memory measurement (0: skip it)"
    )
    p.add_argument(
        "--scipy-trajectories", type=options.count, default=8, help="trajectories integrated one by one by SciPy"
    )
    p.add_argument(
        "--devices",
        type=options.count,
        default=os.cpu_count() or 1,
        help="JAX host devices (one per core; sets XLA_FLAGS for this process before JAX starts its backend)",
    )
    p.add_argument(
        "--reference-batch",
        type=int,
        default=1024,
        help="batch of the reference-family rows: the §6.1 loop with its built-in reference and sampled (0: skip)",
    )
    p.add_argument(
        "--reference-levels",
        nargs="+",
        choices=[str(x) for x in _levels()],
        default=[str(x) for x in _levels()],
        help="levels of the reference-family rows",
    )
    p.add_argument(
        "--export-samples",
        type=int,
        default=200,
        help="periods of the closed-loop run each exported control step (every type x level x law) is checked over (0: skip)",
    )
    p.add_argument("--cc", default="cc", help="the C compiler of the exported steps ('none': skip their C)")
    _slow_block_options(p)
    _tuner_options(p)
    p.add_argument("--worker", choices=("compile", "memory"), help=argparse.SUPPRESS)
    p.add_argument("--case", help=argparse.SUPPRESS)
    p.add_argument("--worker-batch", type=options.count, default=256, help=argparse.SUPPRESS)
    return p


def _device_options(p) -> None:
    """The precision, the chunking and the baselines' reach: what a GPU run sets."""
    from wmrjax.cli import options

    p.add_argument(
        "--dtype",
        choices=("float64", "float32"),
        default="float64",
        help="precision of wmrjax's rollouts and gradients (the NumPy, C and SciPy baselines stay float64)",
    )
    p.add_argument(
        "--chunk",
        type=options.count,
        default=None,
        help="batch_map's examples per chunk (default: the library's, 512 on CPUs and one chunk on a GPU) "
        "[trajectories]",
    )
    p.add_argument(
        "--baseline-max-batch",
        type=options.count,
        default=None,
        help="NumPy and C rows only for batches up to this size (default: every batch) [trajectories]",
    )


def _slow_block_options(p) -> None:
    """The blocks that take minutes: the memory model's calibration and the cold starts."""
    p.add_argument(
        "--memory-estimates",
        action=argparse.BooleanOptionalAction,
        default=True,
        help="the memory model against measured peaks in fresh processes (minutes)",
    )
    p.add_argument(
        "--cold-start",
        nargs="*",
        default=[],
        metavar="JOB",
        help="default jobs timed in fresh processes, cold (empty compilation cache) and warm: names from "
        "benchmarks.benchmark.cold_start_jobs(), or 'all' (tens of minutes); none: skip",
    )


def _levels():
    from wmrjax import Level

    return list(Level)


def _tuner_options(p) -> None:
    """The C ceiling's source and the tuner timing's options."""
    from wmrjax.cli import options

    here = Path(__file__).resolve().parent.parent
    p.add_argument(
        "--c-source",
        type=Path,
        default=here / "benchmarks" / "bench" / "closed_loop_simd.c",
        help="the hand-vectorised C loop (the ceiling; skipped if missing)",
    )
    p.add_argument(
        "--tuner-problems",
        nargs="*",
        default=["section_6_1_plant", "car_schedule"],
        help="shipped tuning problems whose gradient program is timed (none: skip)",
    )
    p.add_argument(
        "--tuner-rounds", type=options.count, default=3, help="alternating rounds of the tuner timing (best kept)"
    )
    p.add_argument(
        "--tuner-baseline",
        type=Path,
        default=None,
        help="a checkout of another commit: its tuner is timed side by side with this one's",
    )


def _run_worker(a) -> int:
    """A fresh-process worker: its measurement printed as JSON."""
    import json

    machine.use_compilation_cache(a)
    res = (
        compile_worker(a.case, a.worker_batch)
        if a.worker == "compile"
        else memory_worker(a.memory_steps, a.memory_batch)
    )
    print(json.dumps(res))
    return 0


def _compile_summary(a) -> dict:
    """Compile times in fresh processes: the section 6.1 loss, and every type x level with ``all``."""
    sec = compile_table(["section_6_1"], a.grad_batch, a.devices)["section_6_1"]
    return {
        "what": "first call (trace + compile) in a fresh process with an empty persistent cache; "
        "cached: a later process reading JAX's persistent compilation cache",
        "forward_s": sec["forward_s"],
        "gradient_s": sec["gradient_s"],
        "forward_cached_s": sec["forward_cached_s"],
        "gradient_cached_s": sec["gradient_cached_s"],
        "gradient_mode": sec["mode"],
        "gradient_method": "wmrjax.batch_value_and_grad (section 6.1); wmrjax.value_and_grad (by_type)",
        "by_type_loss": f"mean squared output error of a vmapped {N_STEPS}-step rollout (dt 0.01) on "
        "a circle, gradient with respect to the Hurwitz coefficients (m x r)",
        "by_type": compile_table(_compile_cases(), 64, a.devices) if a.compile_types == "all" else {},
    }


def _memory_summary(a, env: dict) -> dict:
    """The gradient's peak memory, measured in a fresh process, and printed."""
    m = _worker(
        [
            "--worker",
            "memory",
            "--memory-steps",
            str(a.memory_steps),
            "--memory-batch",
            str(a.memory_batch),
            "--no-compile-cache",
        ],
        dict(env),
    )
    print(
        f"memory: gradient of {a.memory_steps} steps x {a.memory_batch} trajectories: peak RSS "
        f"{m['peak_rss_gb']:.2f} GB ({m['mode']}, {m['wall_s']:.1f} s)",
        flush=True,
    )
    return m


def _print_summary(s: dict, out: Path) -> None:
    """The summary's headline figures and where it was written."""
    g = s["gradient"]
    print(
        f"scipy solve_ivp: {s['scipy_solve_ivp_one_at_a_time']['equivalent_traj_steps_per_s'] / 1e6:.4f} M/s; "
        f"gradient/forward = {g['ratio_grad_over_forward']:.2f} ({g['mode']}; B = {g['batch']}, "
        f"{g['n_parameters']} parameters), {s['gradient_many']['ratio_grad_over_forward']:.2f} with "
        f"{s['gradient_many']['n_parameters']} ({s['gradient_many']['mode']})"
    )
    print(f"wrote {out}/summary.json")


def main(argv=None) -> int:

    p = _parser()
    a = p.parse_args(argv)
    machine.configure_xla(a.devices)  # before JAX starts its backend (a worker's too)
    if a.worker:
        return _run_worker(a)
    unknown = [n for n in a.cold_start if n not in cold_start_jobs() and a.cold_start != ["all"]]
    if unknown:  # before any work
        p.error(f"argument --cold-start: unknown job(s) {unknown}; expected 'all' or some of {list(cold_start_jobs())}")
    running.prepare_output(p, a.out)
    machine.use_compilation_cache(a)
    s = run(
        a.out,
        a.batches,
        a.reps,
        a.grad_batch,
        a.grad_batches,
        a.scipy_trajectories,
        a.c_source,
        many_forward=a.compile_types != "none",
        dtype=a.dtype,
        chunk=a.chunk,
        baseline_max_batch=a.baseline_max_batch,
    )
    if a.reference_batch > 0:
        s["reference_families"] = {
            "what": "jit(vmap) rollout of the §6.1 loop (dynamic law, e = 0, poles -1, dt 0.01, 1000 steps) with "
            "its built-in reference (62) and the same path sampled at 10 and 100 Hz (quintic spline): first-call "
            "compile seconds, best run seconds of 3 alternating rounds, ratios to the built-in reference",
            "batch": a.reference_batch,
            "levels": reference_rows(a.reference_batch, a.reps, tuple(a.reference_levels)),
        }
    if a.export_samples > 0:
        cc = None if a.cc == "none" or shutil.which(a.cc) is None else a.cc
        s["export"] = {
            "what": f"the exported control step (wmrjax.export) of every type x level x law, checked over a "
            f"closed-loop run of {a.export_samples} periods of {EXPORT_PERIOD} s of the simulator's digital "
            "controller (circle, the row's example geometry, poles -1.5): largest differences relative to each "
            "output's largest magnitude; the C step's seconds per call, timed from C (best of 5 loops of "
            "20 000 calls), compiled with " + (f"{cc} " + " ".join(_c_flags()) if cc else "no compiler"),
            "rows": export_rows(a.export_samples, cc),
        }
    # compile times and memory in fresh processes (nothing compiled or cached beforehand)
    env = dict(os.environ)
    if a.compile_types != "none":
        s["compile"] = _compile_summary(a)
    if a.memory_batch > 0:
        s["memory"] = _memory_summary(a, env)
    if a.tuner_problems:
        s["tuner"] = tuner_times(a.tuner_problems, a.tuner_baseline, a.tuner_rounds)
    if a.memory_estimates:
        s["memory_estimates"] = memory_estimates()
    if a.cold_start:
        jobs = cold_start_jobs()
        names = list(jobs) if a.cold_start == ["all"] else a.cold_start
        s["cold_start"] = {
            "what": "wall seconds of each default job in a fresh process: cold (empty persistent compilation "
            "cache), then warm (the cache the cold run wrote); compile_share = 1 - warm / cold",
            "jobs": cold_start_rows({n: jobs[n] for n in names}),
        }
    common.write_json(a.out / "summary.json", s)
    _print_summary(s, a.out)
    outside = [k for k, m in s.get("memory_estimates", {}).items() if not m["within"]]
    if outside:  # the model no longer bounds what it predicts: the refusals it drives are wrong
        print(f"error: memory estimates outside their factor: {', '.join(outside)}", file=sys.stderr)
        return 1
    return 0


if __name__ == "__main__":
    sys.exit(main())
