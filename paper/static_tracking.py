r"""Static feedback linearization for every type (paper §4): posture tracking for (3,0)
(Prop 3, eqs 12/14) and point tracking for (2,0), (2,1), (1,1), (1,2) (Table 3, Props 4-5,
Remark 11), at velocity and torque level.

For each type and level: a circle and a figure-eight from a perturbed start, and a batch of
random smooth references (:func:`wmrjax.references.random_smooth`) from random initial
conditions (point within +-0.5 m of the reference's start, any heading, steering within
+-0.3 rad of its reference, at rest).

    python -m paper.static_tracking --out results/static_tracking [--n-random 1024]

Writes ``summary.json`` (per type and level: final error quantiles, fraction converged,
fraction flagged singular, min |det K|, max ||z3||) and one PNG per type.
"""

from __future__ import annotations

import math
import sys
import time

from paper import common

KINDS = ("(3,0)", "(2,0)", "(2,1)", "(1,1)", "(1,2)")


def _start(ctrl, posture: bool, params, key):
    """Random initial state: the tracked point near the reference's start, at rest."""
    import jax
    import jax.numpy as jnp

    from wmrjax.controllers import Space, Task, place

    k1, k2, k3 = jax.random.split(key, 3)
    th = jax.random.uniform(k2, (), minval=-math.pi, maxval=math.pi)
    # heading: any (the point task), or within 0.3 rad of the reference's (the posture task)
    d_th = 0.3 * th / math.pi if posture else th - params.reference.posture(0.0)[2]
    d_steer = jnp.zeros(ctrl.robot.delta_s)
    if ctrl.row.steering_index is not None:
        d_steer = d_steer.at[-1].set(jax.random.uniform(k3, (), minval=-0.3, maxval=0.3))
    if ctrl.robot.delta_m == 1:  # the steering wheel that is not an output: random angle
        d_steer = d_steer.at[0].set(jax.random.uniform(k3, (), minval=-1.0, maxval=1.0))
    dp = jax.random.uniform(k1, (2,), minval=-0.5, maxval=0.5)
    error = jnp.concatenate([dp, d_th[None], d_steer])
    return place(ctrl, params, error, Space.PHYSICAL, Task.POSTURE if posture else Task.POINT, 1.0, rest=True)


def _point_error(ctrl, posture: bool, t, z, params):
    """(point error [m], heading error [rad] for the posture task, else 0)."""
    import jax.numpy as jnp

    e = ctrl.error(t, z, params)[0]
    return jnp.hypot(e[0], e[1]), (jnp.abs(e[2]) if posture else 0.0 * e[0])


def _named_references(ctrl, g, posture: bool, dt: float, n_steps: int, out: dict) -> dict:
    """One run on a circle and one on a figure eight: their summaries into ``out``, their traces returned."""
    import jax
    import numpy as np

    import wmrjax as w
    from wmrjax import references as R

    traces = {}
    for ref in (R.circle(radius=3.0, omega=0.4), R.figure_eight(size=4.0, omega=0.25)):
        name = ref.name
        params = ctrl.params(ref, poles=1.0, geometry=g)
        z0 = _start(ctrl, posture, params, jax.random.PRNGKey(1))
        ctrl.check_regular(z0, params)
        tr = w.simulate(ctrl, z0, params, dt=dt, n_steps=n_steps, save_every=max(1, n_steps // 300))
        ep, eh = (
            np.asarray(a) for a in jax.vmap(lambda t, z: _point_error(ctrl, posture, t, z, params))(tr.t, tr.state)
        )
        pts = np.asarray(jax.vmap(lambda z: ctrl.outputs(z, params))(tr.state))
        refp = np.asarray(jax.vmap(ref.position)(tr.t))
        traces[name] = dict(t=np.asarray(tr.t), state=pts, ref=refp, ep=ep)
        out[name] = {
            "final_point_error_m": float(ep[-1]),
            "final_heading_error_rad": float(eh[-1]),
            "min_abs_det_K": float(tr.diagnostics.min_margin),
            "failed": bool(tr.diagnostics.failed),
            "max_norm_z3": float(np.max(np.linalg.norm(np.asarray(jax.vmap(ctrl.z3)(tr.state)), axis=-1)))
            if ctrl.row.z3
            else None,
            "final_heading_error_vs_reference_rad": float(tr.diagnostics.internal.heading_error),
            "turned_round": bool(tr.diagnostics.internal.turned_round),
        }
    return traces


def _random_runs(ctrl, g, posture: bool, n_random: int, dt: float, n_steps: int, seed: int):
    """``n_random`` runs on random smooth references from random starts, one compiled batch:
    ``(ep, eh, diagnostics, initial margins, max ||z3||, wall seconds including compile)``."""
    import jax
    import jax.numpy as jnp
    import numpy as np

    import wmrjax as w
    from wmrjax import references as R

    key = jax.random.PRNGKey(seed)
    k_ref, k_ic = jax.random.split(key)

    def one(kr, ki):
        ref = R.random_smooth(kr, n_modes=3, speed=1.0, min_speed=0.3, max_omega=0.6, start_scale=2.0)
        params = ctrl.params_unchecked(ref, 1.0, g)
        z0 = _start(ctrl, posture, params, ki)
        tr = w.simulate(ctrl, z0, params, dt=dt, n_steps=n_steps, save_every=max(1, n_steps // 100))
        ep, eh = _point_error(ctrl, posture, tr.t[-1], tr.final_state, params)
        z3n = jnp.max(jnp.linalg.norm(jax.vmap(ctrl.z3)(tr.state), axis=-1)) if ctrl.row.z3 else 0.0
        return ep, eh, tr.diagnostics, ctrl.margin(z0, params), z3n

    t0 = time.perf_counter()
    ep, eh, diag, m0, z3n = jax.jit(jax.vmap(one))(jax.random.split(k_ref, n_random), jax.random.split(k_ic, n_random))
    jax.block_until_ready(ep)
    wall = time.perf_counter() - t0
    return np.asarray(ep), np.asarray(eh), diag, m0, np.asarray(z3n), wall


def run_case(kind, level, n_random, t_final, dt, seed, tol):
    import numpy as np

    import wmrjax as w

    task = w.Task.POSTURE if w.robot_type(kind).omnidirectional else w.Task.POINT
    ctrl = w.controller(kind, level, task)
    posture = ctrl.task == w.Task.POSTURE  # (3,0): the heading is an output too
    g = ctrl.row.default_geometry
    n_steps = int(round(t_final / dt))
    out = {"task": task, "geometry": g._asdict(), "poles": 1.0, "outputs": ctrl.row.regularity}
    traces = _named_references(ctrl, g, posture, dt, n_steps, out)
    ep, eh, diag, m0, z3n, wall = _random_runs(ctrl, g, posture, n_random, dt, n_steps, seed)
    failed = np.asarray(diag.failed)
    ok = ~failed
    turned = np.asarray(diag.internal.turned_round)
    conv = ok & (ep < tol) & (eh < tol) & ~turned
    q = common.quantiles
    out["random"] = {
        "n_runs": int(n_random),
        "t_final": t_final,
        "dt": dt,
        "initial_conditions": "tracked point uniform within +-0.5 m of the reference's start, any heading "
        "((3,0): +-0.3 rad), steering within +-0.3 rad of its reference, at rest",
        "final_point_error_m": q(ep[ok]),
        **({"final_heading_error_rad": q(eh[ok])} if posture else {}),
        "fraction_converged": float(conv.mean()),
        "converged_definition": f"not flagged singular, final point error < {tol} m"
        + (f" and heading error < {tol} rad" if posture else "")
        + ", not turned round",
        "fraction_point_tracked": float((ok & (ep < tol) & (eh < tol)).mean()),
        "point_tracked_definition": f"not flagged singular, final point error < {tol} m"
        + (f" and heading error < {tol} rad" if posture else "")
        + ", whatever the heading (converged, or turned round)",
        "fraction_turned_round": float(turned.mean()),
        "fraction_point_tracked_but_turned_round": float((ok & (ep < tol) & turned).mean()),
        "turned_round_definition": "final heading more than pi/2 away from the reference heading (path tangent, "
        "forward axis x2): the point is tracked with the robot facing backwards",
        "final_abs_heading_error_vs_reference_rad": q(np.abs(np.asarray(diag.internal.heading_error))[ok]),
        "fraction_flagged_singular": float(failed.mean()),
        "fraction_flagged_inaccurate": float(np.asarray(diag.inaccurate).mean()),
        "flagged_definition": "failed in simulate: singular (margin floor, or det K changed sign between steps), "
        "inaccurate (a step's error estimate above 1e-3, often on the way to the singular "
        "set) or non-finite; fraction_flagged_singular counts every failed run, whatever the "
        "cause, fraction_flagged_inaccurate the inaccurate ones",
        "min_abs_det_K_over_runs": float(np.min(np.asarray(diag.min_margin))),
        "min_initial_abs_det_K": float(np.min(np.asarray(m0))),
        "max_norm_z3": q(z3n[ok]) if ctrl.row.z3 else None,
        "z3_note": "z3 = theta (and a steering angle) integrated unwrapped: on references whose speed is "
        "not L1 (these never stop) theta keeps turning, so ||z3|| grows with the horizon; Prop 5 "
        "bounds it for L1 speeds",
        "wall_time_s_including_compile": wall,
    }
    return out, traces, (ep[ok], eh[ok])


def run(
    out_dir, n_random=1024, t_final=15.0, dt=0.01, seed=0, tol=1e-2, kinds=KINDS, levels=None, progress=None
) -> dict:
    """The experiment on ``kinds`` x ``levels`` (None: every :class:`wmrjax.Level`); its summary."""
    common.enable_x64()
    import wmrjax as w

    levels = tuple(w.Level) if levels is None else levels

    summary = {
        "experiment": "static_tracking",
        "controller": "static feedback linearization (Prop 3 for (3,0); Table 3, eqs 27-28, Remark 11)",
        "poles": "all at -1",
        "cases": {},
    }
    for kind in kinds:
        per_level = {}
        for level in levels:
            t0 = time.perf_counter()
            if progress is not None:
                progress(f"{kind} {level}: compiling and running {n_random} random runs and two named references")
            res, traces, errs = run_case(kind, level, n_random, t_final, dt, seed, tol)
            per_level[level] = (traces, errs)
            summary["cases"][f"{kind} {level}"] = res
            r = res["random"]
            print(
                f"{kind} {level}: converged {r['fraction_converged']:.3f}, turned round "
                f"{r['fraction_turned_round']:.3f}, singular {r['fraction_flagged_singular']:.3f}, "
                f"median final point error {r['final_point_error_m'].get('q50', float('nan')):.2e} m, "
                f"min |det K| {r['min_abs_det_K_over_runs']:.3g} ({time.perf_counter() - t0:.1f} s)",
                flush=True,
            )
        label = "position error [m]" if w.robot_type(kind).omnidirectional else "point error |h(X) - p_ref| [m]"
        common.tracking_figure(out_dir, kind, per_level, prefix="static", error_label=label)
        common.write_json(out_dir / "summary.json", summary)  # progress: rewritten after each type
    return summary


def main(argv=None) -> int:
    return common.tracking_cli(argv, __doc__, "results/static_tracking", KINDS, run)


if __name__ == "__main__":
    sys.exit(main())
