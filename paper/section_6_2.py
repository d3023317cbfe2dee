r"""§6.2 of the paper: hybrid parking of a (2,0) robot along the reference (66), which stops
at the origin at t = 10 s: dynamic linearization (Table 4, eq 39; poles -1) until the robot
enters the disk x^2 + y^2 <= sqrt(2)/10, then the time-varying stabilizer (a documented
reconstruction of CL3 of Pomet et al. 1992, lambda = 40, psi(theta) = theta; see
wmrjax.controllers.hybrid and errata.md) with its own clock.

    python -m paper.section_6_2 --out results/section_6_2

Writes ``summary.json`` (t_switch, state_at_switch, eta1_at_switch, min_eta1_before_switch,
final_distance, final_heading, a lemma2 check up to the switch, and a batch of initial
conditions around the paper's: fraction parked, switch-time distribution),
``fig10_paths.png``, ``fig11_eta1.png``, ``batch.png`` and ``trajectory.npz``.
"""

from __future__ import annotations

import math
import sys

from paper import common
from wmrjax.cli import options


def setup(r_switch=None, lam=None):
    import jax.numpy as jnp

    from wmrjax import references
    from wmrjax.controllers import hybrid as H

    hy = H.hybrid_parking()
    params = hy.params(
        references.paper_66(),
        poles=1.0,
        r_switch=H.PAPER_R_SWITCH if r_switch is None else r_switch,
        lam=H.PAPER_LAMBDA if lam is None else lam,
    )
    # x(0) = 10 sqrt(2)/6 m, y(0) = 2.54 m, xdot(0) = ydot(0) = -0.5 m/s
    zeta0 = jnp.array([[10.0 * math.sqrt(2.0) / 6.0, 2.54], [-0.5, -0.5]])
    return hy, params, zeta0


def _parked(final, tol_pos, tol_head):
    import numpy as np

    d = np.hypot(final[..., 0], final[..., 1])
    h = np.abs(np.angle(np.exp(1j * final[..., 2])))
    return d, h, (d <= tol_pos) & (h <= tol_head)


def run(
    out,
    dt=0.01,
    t_final=60.0,
    n_batch=1024,
    tol_pos=0.05,
    tol_head=0.1,
    r_switch=None,
    lam=None,
    seed=0,
    eps=1e-2,
    progress=None,
) -> dict:
    say = progress or (lambda msg: print(msg, flush=True))
    common.enable_x64()
    import jax
    import jax.numpy as jnp
    import numpy as np

    import wmrjax as w

    hy, params, zeta0 = setup(r_switch, lam)
    n_steps = int(round(t_final / dt))
    z0 = hy.initial_state(zeta0, params)
    say("compiling and running the section 6.2 hybrid loop")
    tr = w.simulate(hy, z0, params, dt=dt, n_steps=n_steps)
    t, st, u = np.asarray(tr.t), np.asarray(tr.state.tracking), np.asarray(tr.control)
    fin = jax.tree_util.tree_map(np.asarray, tr.final_state)  # NumPy from here on
    switched = bool(fin.switched)
    t_sw = float(fin.t_switch) if switched else None
    ref = params.tracking.reference
    ref_post = np.asarray(jax.vmap(ref.posture)(jnp.asarray(np.minimum(t, 10.0))))
    eta1_ref = np.asarray(jax.vmap(lambda s: jnp.linalg.norm(ref.velocity(s)))(jnp.asarray(np.minimum(t, 10.0))))
    summary = _summary(params, z0, tr, fin, t, st, u, switched, t_sw, dt, t_final, tol_pos, tol_head)
    if switched:
        say("Lemma 2 up to the switch")
        summary["lemma2"] = _lemma2_to_switch(hy, params, z0, t_sw, dt, eps)
    batch = None
    if n_batch:
        say(f"compiling and running a batch of {n_batch} initial conditions")
        summary["batch"], batch = _batch(hy, params, zeta0, n_batch, seed, dt, n_steps, tol_pos, tol_head)
    out.mkdir(parents=True, exist_ok=True)
    _figures(out, t, st, u, ref_post, eta1_ref, t_sw, float(params.r_switch), batch)
    common.write_npz(
        out / "trajectory.npz",
        t=t,
        state=st,
        control=u,
        reference=ref_post,
        mode=np.asarray(tr.state.mode),
        state_names=np.array(hy.state_names[:4]),
    )
    common.write_json(out / "summary.json", summary)
    return summary


def _summary(params, z0, tr, fin, t, st, u, switched, t_sw, dt, t_final, tol_pos, tol_head) -> dict:
    """summary.json without the lemma2 and batch blocks, from the hybrid run."""
    import numpy as np

    before = t < (t_sw if switched else np.inf)
    i_sw = int(np.searchsorted(t, t_sw - 0.5 * dt)) if switched else None
    d_fin, h_fin, _ = _parked(np.asarray(fin.tracking), tol_pos, tol_head)
    return {
        "experiment": "section_6_2",
        "paper": "d'Andrea-Novel, Campion & Bastin, IJRR 14(6) 1995, section 6.2",
        "robot": "(2,0)",
        "geometry": {"e": 0.0},
        "controller": "dynamic feedback linearization (eq 39, poles -1), then the time-varying stabilizer",
        "stabilizer": "reconstruction of CL3 (Pomet et al. 1992) documented in errata.md, psi(theta) = theta",
        "reference": "eq (66): x_ref = y_ref = 1e-2 sqrt(2)/6 (10 - t)^3, at rest at the origin for t >= 10 s",
        "r_switch": float(params.r_switch),
        "r_switch_squared": float(params.r_switch) ** 2,
        "lambda": float(params.lam),
        "dt": dt,
        "t_final": t_final,
        "initial_state": dict(zip(["x", "y", "theta", "chi1"], map(float, z0.tracking))),
        "switched": switched,
        "t_switch": t_sw,
        "state_at_switch": dict(zip(["x", "y", "theta", "chi1"], map(float, fin.at_switch))) if switched else None,
        # e = 0: the linearizing law's eta1 is chi1; the stabilizer then starts from its own eta1
        "eta1_at_switch": float(fin.at_switch[3]) if switched else None,
        "eta1_stabilizer_after_switch": float(u[i_sw, 0]) if switched else None,
        "min_eta1_before_switch": float(np.min(np.abs(u[before, 0]))),
        "final_distance": float(d_fin),
        "final_heading": float(np.angle(np.exp(1j * fin.tracking[2]))),
        "max_abs_heading_last_2pi_s": float(np.max(np.abs(np.angle(np.exp(1j * st[t >= t_final - 2 * math.pi, 2]))))),
        "distance_at": {
            f"{s:g}": float(np.hypot(*st[int(round(s / dt)), :2])) for s in (10, 20, 30, 45, 60) if s <= t_final
        },
        "nonfinite": bool(tr.diagnostics.nonfinite),
        "failed": bool(tr.diagnostics.failed),
    }


def _lemma2_to_switch(hy, params, z0, t_sw: float, dt: float, eps: float) -> dict:
    """Lemma 2 of the tracking phase up to the switch (M1 -> 0 at rest: it certifies nothing beyond)."""
    import jax.numpy as jnp

    from wmrjax import certify as C

    ctrl, tp = hy.tracking, params.tracking
    cert = C.lemma2(ctrl, tp, t_final=t_sw, eps=eps, n_t=max(int(round(t_sw / dt)) + 1, 3))
    e0 = float(jnp.linalg.norm(ctrl.error(0.0, z0.tracking, tp)))
    return {
        "eps": eps,
        "horizon": t_sw,
        "zeta0_norm": e0,
        "radius_paper": float(cert.paper.radius),
        "argmin_F_paper": float(cert.paper.argmin),
        "condition_52_paper": bool(e0 <= float(cert.paper.radius)),
        "radius_exact_norm": float(cert.exact_norm.radius),
        "condition_52_exact_norm": bool(e0 <= float(cert.exact_norm.radius)),
        "min_M1": float(jnp.min(cert.paper.m1)),
    }


def _batch(hy, params, zeta0, n_batch: int, seed: int, dt: float, n_steps: int, tol_pos: float, tol_head: float):
    """A batch of initial conditions around the paper's: ``(its summary block, (switch times,
    final distances of the runs that did not fail))`` for the figure."""
    import jax
    import jax.numpy as jnp
    import numpy as np

    import wmrjax as w

    k1, k2 = jax.random.split(jax.random.PRNGKey(seed))
    dp = jax.random.uniform(k1, (n_batch, 2), minval=-0.3, maxval=0.3)
    dv = jax.random.uniform(k2, (n_batch, 2), minval=-0.2, maxval=0.2)
    zetas = zeta0[None] + jnp.stack([dp, dv], axis=1)
    z0s = jax.vmap(lambda zz: hy.initial_state(zz, params))(zetas)
    fins, diag = jax.jit(
        jax.vmap(
            lambda z: (lambda r: (r.final_state, r.diagnostics))(
                w.simulate(hy, z, params, dt=dt, n_steps=n_steps, save_every=n_steps)
            )
        )
    )(z0s)
    switched_b = np.asarray(fins.switched)
    ok = ~np.asarray(diag.failed)
    d, h, parked = _parked(np.asarray(fins.tracking), tol_pos, tol_head)
    tsw = np.asarray(fins.t_switch)[switched_b]
    q = lambda a: (
        {k: float(np.quantile(a, p)) for k, p in (("min", 0), ("median", 0.5), ("p90", 0.9), ("max", 1))}
        if len(a)
        else None
    )
    block = {
        "n_runs": n_batch,
        "perturbation": "position +-0.3 m, velocity +-0.2 m/s (uniform) around the paper's",
        "tolerance": {"distance_m": tol_pos, "heading_rad": tol_head},
        "fraction_parked": float(np.mean(parked & ok)),
        "fraction_within_distance": float(np.mean((d <= tol_pos) & ok)),
        "fraction_switched": float(np.mean(switched_b)),
        "n_failed": int((~ok).sum()),
        "nonfinite": int(np.asarray(diag.nonfinite).sum()),
        "t_switch_s": q(tsw),
        "final_distance_m": q(d[ok]),
        "final_abs_heading_rad": q(h[ok]),
    }
    return block, (tsw, d[ok])


def _figures(out, t, st, u, ref, eta1_ref, t_sw, r_s, batch):
    import numpy as np

    plt = common.pyplot()
    fig, ax = plt.subplots(figsize=(5.8, 5.8))
    ax.plot(ref[:, 0], ref[:, 1], "k--", lw=1.2, label="reference (66)")
    ax.plot(st[:, 0], st[:, 1], "C0", lw=1.4, label="robot")
    th = np.linspace(0, 2 * np.pi, 200)
    ax.plot(r_s * np.cos(th), r_s * np.sin(th), "C3:", lw=1.0, label=f"switching disk r_s = {r_s:.3f} m")
    if t_sw is not None:
        i = int(np.searchsorted(t, t_sw - 1e-9))
        ax.plot(st[i, 0], st[i, 1], "C3o", ms=5, label=f"switch, t = {t_sw:.2f} s")
    ax.plot(st[0, 0], st[0, 1], "C0s", ms=5)
    ax.set_xlabel("x [m]")
    ax.set_ylabel("y [m]")
    ax.set_title("Fig. 10: reference and robot Cartesian trajectories")
    ax.axis("equal")
    ax.grid(alpha=0.3)
    ax.legend(fontsize=8)
    inset = ax.inset_axes([0.58, 0.08, 0.38, 0.38])
    inset.plot(st[:, 0], st[:, 1], "C0", lw=0.8)
    inset.plot(r_s * np.cos(th), r_s * np.sin(th), "C3:", lw=0.8)
    inset.set_xlim(-1.2 * r_s, 1.2 * r_s)
    inset.set_ylim(-1.2 * r_s, 1.2 * r_s)
    inset.set_title("near the goal", fontsize=7)
    inset.tick_params(labelsize=6)
    common.save_figure(fig, out / "fig10_paths.png")
    plt.close(fig)

    fig, axs = plt.subplots(2, 1, figsize=(6.8, 5.8), sharex=True)
    axs[0].plot(t, u[:, 0] - eta1_ref, "C0")
    axs[0].set_ylabel("eta1 - eta1_ref [m/s]")
    axs[1].plot(t, np.hypot(st[:, 0], st[:, 1]), "C2", label="distance to the goal [m]")
    axs[1].plot(t, np.angle(np.exp(1j * st[:, 2])), "C1", lw=0.8, label="heading theta [rad]")
    axs[1].set_ylabel("[m], [rad]")
    axs[1].legend(fontsize=8)
    for a in axs:
        if t_sw is not None:
            a.axvline(t_sw, color="C3", ls="--", lw=1.0, label="switch")
        a.grid(alpha=0.3)
    axs[0].legend(fontsize=8)
    axs[0].set_title("Fig. 11: error in eta1 (tracking, then the time-varying law)")
    axs[1].set_xlabel("t [s]")
    common.save_figure(fig, out / "fig11_eta1.png")
    plt.close(fig)

    if batch is not None:
        tsw, d = batch
        fig, axs = plt.subplots(1, 2, figsize=(9, 3.6))
        axs[0].hist(tsw, bins=40, color="C0")
        axs[0].set_xlabel("switch time [s]")
        axs[0].set_ylabel("runs")
        axs[1].hist(np.log10(np.maximum(d, 1e-12)), bins=40, color="C2")
        axs[1].set_xlabel("log10 final distance to the goal [m]")
        for a in axs:
            a.grid(alpha=0.3)
        fig.suptitle("batch around the paper's initial conditions")
        common.save_figure(fig, out / "batch.png")
        plt.close(fig)


def main(argv=None) -> int:
    from wmrjax.cli import machine, running

    p = options.parser(__doc__.splitlines()[0], "results/section_6_2")
    p.add_argument("--dt", type=options.positive, default=0.01, help="RK4 step [s]")
    p.add_argument(
        "--t-final",
        type=options.positive,
        default=60.0,
        help="horizon [s]; must exceed 10 s, when the reference (66) comes to rest",
    )
    p.add_argument("--n-batch", type=options.count, default=1024, help="initial conditions around the paper's")
    p.add_argument(
        "--tol-distance", type=options.positive, default=0.05, help="parked: distance to the goal <= this [m]"
    )
    p.add_argument("--tol-heading", type=options.positive, default=0.1, help="parked: |heading| <= this [rad]")
    p.add_argument(
        "--r-switch",
        type=options.positive,
        default=None,
        help="switching radius [m] (None: the paper's sqrt(sqrt(2)/10) = 0.376 m)",
    )
    p.add_argument(
        "--lam", type=options.positive, default=None, help="stabilizer gain lambda [1/s] (None: the paper's 40)"
    )
    a = p.parse_args(argv)
    machine.configure_xla()  # before JAX starts its backend
    if not a.t_final > 10.0:
        p.error(
            f"argument --t-final: must exceed 10 s (the reference (66) stops at t = 10 s and parking follows), "
            f"got {a.t_final}"
        )
    n = machine.check_horizon(p, t_final=a.t_final, dt=a.dt, n_state=10)  # the single run keeps every step
    if a.n_batch:  # the batch keeps each run's first and last state
        machine.check_horizon(
            p, t_final=a.t_final, dt=a.dt, batch=a.n_batch, n_state=10, saved_every=n, fix="lower --n-batch"
        )
    s = running.work(
        p,
        a,
        lambda progress: run(
            a.out, a.dt, a.t_final, a.n_batch, a.tol_distance, a.tol_heading, a.r_switch, a.lam, progress=progress
        ),
    )
    print(
        f"section 6.2: switch at t = {s['t_switch']} s, state {s['state_at_switch']}, eta1 = {s['eta1_at_switch']}; "
        f"final distance {s['final_distance']:.4g} m, heading {s['final_heading']:.3g} rad"
    )
    if "batch" in s:
        b = s["batch"]
        median = (b["t_switch_s"] or {}).get("median")
        print(
            f"batch of {b['n_runs']}: parked {b['fraction_parked']:.3f} (within distance {b['fraction_within_distance']:.3f}), "
            + (f"switch time median {median:.2f} s" if median is not None else "no run switched")
        )
    print(f"wrote {a.out}/summary.json, fig10_paths.png, fig11_eta1.png, batch.png, trajectory.npz")
    return 0


if __name__ == "__main__":
    sys.exit(main())
