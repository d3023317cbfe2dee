r"""Side-by-side speed of the §6.1 closed-loop batch rollout (RK4, dt = 0.01, 1000 steps, float64).

Compares, in one run and on the same initial conditions: wmrjax (``batch_map``: one
device per core, 512-trajectory chunks, with and without the per-step error estimate of
``simulate``; and plain ``jit(vmap)`` on one device), a NumPy
implementation vectorised over the batch, SciPy ``solve_ivp`` one trajectory at a time,
and the hand-vectorised C loop ``../shared/bench/closed_loop_simd.c`` (the ceiling; skipped
with a note if no C compiler or source is found). Also times a reverse-mode gradient of a
batch tracking loss with respect to the gains relative to the forward pass.

    python -m experiments.benchmark --out results/benchmark [--batches 1024 16384 65536]

Writes ``summary.json`` (trajectory-steps per second and ratios). No figure: numbers only.
"""

from __future__ import annotations

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

from experiments import common

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
    return np.stack([p - 0.54 + 0.1 * ((b % 97) / 97.0 - 0.5), np.full(batch, p + 0.54),
                     np.full(batch, 3 * np.pi / 4), np.full(batch, S2 * (-pd))], axis=1)


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
        x, y, th, c = (a + DT / 6 * (q1 + 2 * q2 + 2 * q3 + q4) for a, q1, q2, q3, q4 in zip((x, y, th, c), k1, k2, k3, k4))
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


def run(out: Path, batches, reps: int, grad_batch: int, scipy_trajs: int, source: Path) -> dict:
    common.enable_x64()
    import jax
    import jax.numpy as jnp
    import numpy as np
    from scipy.integrate import solve_ivp

    import wmrjax as w

    ctrl, params, _, _ = common.section_6_1_setup()
    sim_final = lambda z: w.simulate(ctrl, z, params, dt=DT, n_steps=N_STEPS, save_every=N_STEPS).final_state
    fast = jax.jit(lambda z: w.batch_map(sim_final, z, chunk=512))
    # the same loop without the per-step error estimate (error_tol=None): what the guard costs
    sim_bare = lambda z: w.simulate(ctrl, z, params, dt=DT, n_steps=N_STEPS, save_every=N_STEPS,
                                    error_tol=None).final_state
    bare = jax.jit(lambda z: w.batch_map(sim_bare, z, chunk=512))
    plain = jax.jit(jax.vmap(sim_final))
    rows = {}
    c_res, c_note = c_ceiling(batches, source)
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
        tn, zn = _best_time(lambda: numpy_rollout(S), 1 if b > 20000 else 2)
        row["numpy_vectorised"] = b * N_STEPS / tn
        row["max_abs_diff_wmrjax_vs_numpy"] = float(np.max(np.abs(np.asarray(zf) - zn)))
        if c_res:
            row["c_simd_ceiling"] = c_res[b]
            row["ratio_wmrjax_over_c"] = row["wmrjax_batch_map"] / c_res[b]
            row["ratio_wmrjax_no_error_estimate_over_c"] = row["wmrjax_batch_map_no_error_estimate"] / c_res[b]
            row["ratio_numpy_over_c"] = row["numpy_vectorised"] / c_res[b]
            row["ratio_jit_vmap_1_device_over_c"] = row["wmrjax_jit_vmap_1_device"] / c_res[b]
        rows[str(b)] = row
        print(f"B={b}: wmrjax {row['wmrjax_batch_map'] / 1e6:.2f} M/s (without the error estimate "
              f"{row['wmrjax_batch_map_no_error_estimate'] / 1e6:.2f}; jit(vmap) 1 device "
              f"{row['wmrjax_jit_vmap_1_device'] / 1e6:.2f}), numpy {row['numpy_vectorised'] / 1e6:.2f}"
              + (f", C {c_res[b] / 1e6:.2f} -> ratio {row['ratio_wmrjax_over_c']:.2f}" if c_res else ""), flush=True)

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
    scipy_rate = scipy_trajs * N_STEPS / ts

    # Gradient: reverse mode of a batch tracking loss w.r.t. the gains vs the forward pass.
    zg = jnp.asarray(initial_states_numpy(grad_batch))

    def loss(poles, z0s):
        # gains broadcast per example: each trajectory accumulates its own cotangent and
        # the batch is reduced once at the end (instead of a cross-batch sum every step)
        pb = jnp.broadcast_to(poles, (z0s.shape[0],) + poles.shape)

        def one(z, pl):
            p = params._replace(gains=w.Gains.from_poles(pl))
            tr = w.simulate(ctrl, z, p, dt=DT, n_steps=N_STEPS, save_every=10)
            e = jax.vmap(lambda t, s: ctrl.error(t, s, p)[0])(tr.t, tr.state)  # position errors
            return jnp.mean(jnp.sum(e**2, axis=-1))

        return jnp.mean(w.batch_map(one, z0s, pb, chunk=512))

    poles = jnp.ones((2, 2))
    fwd = jax.jit(loss)
    grad = jax.jit(jax.value_and_grad(loss))
    jac = jax.jit(jax.jacfwd(loss))
    fwd(poles, zg).block_until_ready()
    jax.block_until_ready(grad(poles, zg))
    jax.block_until_ready(jac(poles, zg))
    tf, _ = _best_time(lambda: fwd(poles, zg).block_until_ready(), reps)
    tg, (val, g) = _best_time(lambda: jax.block_until_ready(grad(poles, zg)), reps)
    tj, gj = _best_time(lambda: jax.block_until_ready(jac(poles, zg)), reps)

    summary = {
        "experiment": "benchmark",
        "closed_loop": "section 6.1: (2,0) robot, e = 0, dynamic FL (eq 39), poles -1, reference (62)",
        "integration": {"method": "RK4", "dt": DT, "steps": N_STEPS, "dtype": "float64"},
        "machine": {"cpu_count": os.cpu_count(), "jax_devices": len(jax.devices()), "platform": platform.platform(),
                    "jax_version": jax.__version__, "backend": jax.default_backend()},
        "units": "trajectory-steps per second (batch size x 1000 steps / wall time, best of reps, compile excluded)",
        "rollout": rows,
        "c_ceiling_note": c_note,
        "scipy_solve_ivp_one_at_a_time": {"method": "RK45", "rtol": 1e-8, "atol": 1e-10, "trajectories": scipy_trajs,
                                          "mean_rhs_evaluations": nfev / scipy_trajs,
                                          "equivalent_traj_steps_per_s": scipy_rate},
        "gradient": {"batch": grad_batch, "loss": "mean squared position error, saved every 10 steps",
                     "n_parameters": int(poles.size),
                     "forward_s": tf, "value_and_grad_s": tg, "ratio_grad_over_forward": tg / tf,
                     "forward_mode_jacfwd_s": tj, "ratio_jacfwd_over_forward": tj / tf,
                     "max_abs_diff_reverse_vs_forward_mode": float(np.max(np.abs(np.asarray(g) - np.asarray(gj)))),
                     "loss_value": float(val), "grad_finite": bool(np.all(np.isfinite(np.asarray(g))))},
    }
    for b, row in rows.items():
        row["ratio_wmrjax_over_scipy"] = row["wmrjax_batch_map"] / scipy_rate
    common.write_json(out / "summary.json", summary)
    return summary


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


def main(argv=None) -> int:
    from wmrjax import cli

    p = common.parser(__doc__.splitlines()[0], "results/benchmark", compile_cache=False)   # it times compilation
    p.add_argument("--batches", type=cli.count, nargs="+", default=[1024, 16384, 65536],
                   help="batch sizes of the rollout comparison [trajectories]")
    p.add_argument("--reps", type=cli.count, default=5, help="timed repetitions (best kept)")
    p.add_argument("--grad-batch", type=cli.count, default=1024, help="batch of the gradient timing [trajectories]")
    p.add_argument("--scipy-trajectories", type=cli.count, default=8, help="trajectories integrated one by one by SciPy")
    p.add_argument("--devices", type=cli.count, default=os.cpu_count() or 1,
                   help="JAX host devices (one per core; sets XLA_FLAGS for this process before JAX starts its backend)")
    here = Path(__file__).resolve().parent.parent
    p.add_argument("--c-source", type=Path, default=here.parent / "shared" / "bench" / "closed_loop_simd.c",
                   help="the hand-vectorised C loop (the ceiling; skipped if missing)")
    a = p.parse_args(argv)
    cli.prepare_output(p, a.out)
    cli.use_compilation_cache(a)
    flag = f"--xla_force_host_platform_device_count={a.devices}"
    os.environ["XLA_FLAGS"] = (os.environ.get("XLA_FLAGS", "") + " " + flag).strip()   # read when the backend starts
    s = run(a.out, a.batches, a.reps, a.grad_batch, a.scipy_trajectories, a.c_source)
    g = s["gradient"]
    print(f"scipy solve_ivp: {s['scipy_solve_ivp_one_at_a_time']['equivalent_traj_steps_per_s'] / 1e6:.4f} M/s; "
          f"gradient/forward = {g['ratio_grad_over_forward']:.1f} reverse mode, "
          f"{g['ratio_jacfwd_over_forward']:.1f} forward mode (B = {g['batch']}, {g['n_parameters']} gains)")
    print(f"wrote {a.out}/summary.json")
    return 0


if __name__ == "__main__":
    sys.exit(main())
