r"""Posture tracking by dynamic feedback linearization for every restricted type (Table 4).

For each type (2,0), (2,1), (1,1), (1,2) at velocity and torque level: a circle and a
figure-eight from a perturbed start, and a batch of random smooth references
(:func:`wmrjax.references.random_smooth`) from random initial conditions around them.

    python -m paper.posture_tracking --out results/posture_tracking [--n-random 1024]

Writes ``summary.json`` (per type and level: final posture-error quantiles over the runs
that stayed regular, fraction converged, fraction flagged singular, min margin) and one
PNG per type (paths and errors).
"""

from __future__ import annotations

import sys
import time

from paper import common

KINDS = ("(2,0)", "(2,1)", "(1,1)", "(1,2)")


def _posture_error(xi, xi_ref):
    import numpy as np

    d = np.asarray(xi)[..., :3] - np.asarray(xi_ref)
    d[..., 2] = np.angle(np.exp(1j * d[..., 2]))
    return np.hypot(d[..., 0], d[..., 1]), np.abs(d[..., 2])


def _named_references(ctrl, g, free_heading: bool, t_final: float, dt: float, n_steps: int, out: dict) -> dict:
    """Single runs on a circle and a figure eight from one perturbation, kept for the figure:
    their summaries into ``out``, their traces returned."""
    import jax
    import jax.numpy as jnp
    import numpy as np

    import wmrjax as w
    from wmrjax import references as R
    from wmrjax.controllers import Space, Task, place

    named = {
        r.name: r
        for r in (
            R.circle(radius=3.0, omega=0.4, heading_offset=0.3 if free_heading else 0.0),
            R.figure_eight(size=4.0, omega=0.25, heading_offset=0.3 if free_heading else 0.0),
        )
    }
    pert = jnp.zeros(ctrl.robot.n_state).at[:3].set(jnp.array([0.3, -0.2, 0.1]))  # x, y [m], theta [rad]
    traces = {}
    for name, ref in named.items():
        params = ctrl.params(ref, poles=1.0, geometry=g)
        ctrl.check_reference(params, t_final)
        z0 = place(ctrl, params, pert, Space.PHYSICAL, Task.POSTURE, float(ctrl.reference_branch(params)))
        ctrl.check_regular(z0, params)
        tr = w.simulate(ctrl, z0, params, dt=dt, n_steps=n_steps, save_every=max(1, n_steps // 300))
        post = jax.vmap(ref.posture)(tr.t)
        ep, eh = _posture_error(tr.state, post)
        traces[name] = dict(t=np.asarray(tr.t), state=np.asarray(tr.state), ref=np.asarray(post), ep=ep, eh=eh)
        out[name] = {
            "final_position_error": float(ep[-1]),
            "final_heading_error": float(eh[-1]),
            "min_margin": float(tr.diagnostics.min_margin),
            "failed": bool(tr.diagnostics.failed),
        }
    return traces


def _random_runs(ctrl, g, free_heading: bool, n_random: int, t_final: float, dt: float, n_steps: int, seed: int):
    """Random references x random initial conditions, one compiled batch: ``(final states,
    diagnostics, reference postures at the end, initial margins, reference regular, wall seconds)``."""
    import jax
    import jax.numpy as jnp

    import wmrjax as w
    from wmrjax import references as R
    from wmrjax.controllers import Space, Task, place

    k_ref, k_ic, k_off = jax.random.split(jax.random.PRNGKey(seed), 3)
    n_post = ctrl.robot.n_state

    def draw(kr, ki, ko):
        ref = R.random_smooth(kr, n_modes=3, speed=1.0, min_speed=0.3, max_omega=0.6, start_scale=2.0)
        if free_heading:
            # a crab angle bounded away from 0: at 0 the (1,2) reference itself is singular
            ko1, ko2 = jax.random.split(ko)
            off = jax.random.uniform(ko1, (), minval=0.3, maxval=0.8) * jnp.sign(jax.random.normal(ko2, ()))
            ref = ref.with_heading_offset(off)
        params = ctrl.params_unchecked(ref, 1.0, g)
        dp = jax.random.uniform(ki, (n_post,), minval=-1.0, maxval=1.0)
        scale = jnp.array([0.3, 0.3, 0.15] + [0.1] * ctrl.robot.delta_s)
        return params, place(
            ctrl, params, dp * scale, Space.PHYSICAL, Task.POSTURE, float(ctrl.reference_branch(params))
        )

    params_b, z0_b = jax.vmap(draw)(
        jax.random.split(k_ref, n_random), jax.random.split(k_ic, n_random), jax.random.split(k_off, n_random)
    )

    def one(params, z0):
        tr = w.simulate(ctrl, z0, params, dt=dt, n_steps=n_steps, save_every=n_steps)
        _, m_ref, q_ref = ctrl.reference_margins(params, t_final, 151)
        ref_ok = (jnp.min(m_ref) > 1e-3) & jnp.all(q_ref * ctrl.reference_branch(params) > 0)
        return tr.final_state, tr.diagnostics, params.reference.posture(tr.t[-1]), ctrl.margin(z0, params), ref_ok

    t0 = time.perf_counter()
    zf, diag, post_f, m0, ref_ok = jax.jit(jax.vmap(one))(params_b, z0_b)
    jax.block_until_ready(zf)
    return zf, diag, post_f, m0, ref_ok, time.perf_counter() - t0


def run_case(kind, level, n_random, t_final, dt, seed, tol_pos, tol_head):
    import numpy as np

    import wmrjax as w

    ctrl = w.dynamic_linearization(kind, level)
    g = ctrl.row.default_geometry
    free_heading = bool(ctrl.row.extension.angle_outputs)  # theta is an output: a crab angle is possible
    n_steps = int(round(t_final / dt))
    out = {"geometry": g._asdict(), "poles": 1.0, "relative_degree": ctrl.relative_degree}
    traces = _named_references(ctrl, g, free_heading, t_final, dt, n_steps, out)
    zf, diag, post_f, m0, ref_ok, wall = _random_runs(ctrl, g, free_heading, n_random, t_final, dt, n_steps, seed)
    ep, eh = _posture_error(zf, post_f)
    ref_ok = np.asarray(ref_ok)
    failed = np.asarray(diag.failed)
    ok = ~failed & ref_ok
    conv = ok & (ep < tol_pos) & (eh < tol_head)
    q = common.quantiles
    out["random"] = {
        "n_runs": int(n_random),
        "t_final": t_final,
        "dt": dt,
        "initial_perturbation": "uniform: +-0.3 m in x, y; +-0.15 rad in theta; +-0.1 rad in steering angles",
        "final_position_error_m": q(ep[ok]),
        "final_heading_error_rad": q(eh[ok]),
        "fraction_references_regular": float(ref_ok.mean()),
        "reference_regularity_definition": "margin of (X_e)_ref(t) > 1e-3 on a 151-point grid of [0, t_final], one branch",
        "fraction_converged": float(conv.mean()),
        "converged_definition": f"regular run with final position error < {tol_pos} m and heading error < {tol_head} rad",
        "fraction_flagged_singular": float(failed.mean()),
        "fraction_flagged_inaccurate": float(np.asarray(diag.inaccurate).mean()),
        "flagged_definition": "failed in simulate: singular (margin floor, or det K changed sign between steps), "
        "inaccurate (a step's error estimate above 1e-3, often on the way to the singular "
        "set) or non-finite; fraction_flagged_singular counts every failed run, whatever the "
        "cause, fraction_flagged_inaccurate the inaccurate ones",
        "fraction_flagged_singular_on_regular_references": float(failed[ref_ok].mean()) if ref_ok.any() else None,
        "min_margin_over_runs": float(np.min(np.asarray(diag.min_margin))),
        "min_initial_margin": float(np.min(np.asarray(m0))),
        "wall_time_s_including_compile": wall,
        "note": "quantiles exclude runs flagged singular and runs on irregular references; both are counted",
    }
    return out, traces, (ep[ok], eh[ok])


def run(
    out_dir,
    n_random=1024,
    t_final=15.0,
    dt=0.01,
    seed=0,
    tol_pos=1e-2,
    tol_head=1e-2,
    kinds=KINDS,
    levels=None,
    progress=None,
):
    """The experiment on ``kinds`` x ``levels`` (None: every :class:`wmrjax.Level`); its summary."""
    common.enable_x64()
    import wmrjax as w

    levels = tuple(w.Level) if levels is None else levels
    summary = {
        "experiment": "posture_tracking",
        "controller": "dynamic feedback linearization (Table 4, Prop 8)",
        "poles": "all at -1",
        "cases": {},
    }
    for kind in kinds:
        per_level = {}
        for level in levels:
            t0 = time.perf_counter()
            if progress is not None:
                progress(f"{kind} {level}: compiling and running {n_random} random runs and two named references")
            res, traces, errs = run_case(kind, level, n_random, t_final, dt, seed, tol_pos, tol_head)
            per_level[level] = (traces, errs)
            summary["cases"][f"{kind} {level}"] = res
            r = res["random"]
            print(
                f"{kind} {level}: references regular {r['fraction_references_regular']:.3f}, "
                f"converged {r['fraction_converged']:.3f}, singular {r['fraction_flagged_singular']:.3f}, "
                f"median final position error {r['final_position_error_m'].get('q50', float('nan')):.2e} m "
                f"({time.perf_counter() - t0:.1f} s)",
                flush=True,
            )
        common.tracking_figure(out_dir, kind, per_level)
        common.write_json(out_dir / "summary.json", summary)  # progress: rewritten after each type
    return summary


def main(argv=None) -> int:
    return common.tracking_cli(argv, __doc__, "results/posture_tracking", KINDS, run)


if __name__ == "__main__":
    sys.exit(main())
