r"""§6.1 of the paper: posture tracking of the non-singular reference (62) by a (2,0) robot.

Dynamic feedback linearization at velocity level (Table 4, eq 39), e = 0, both error
poles at -1 per axis, initial conditions (63), 10 s, RK4 with dt = 0.01 s.

    python -m paper.section_6_1 --out results/section_6_1

Writes ``summary.json`` (with a ``lemma2`` block: certified radii for three K2 bounds and
an empirical check over 4096 initial errors), ``trajectories.npz`` (t, state, control,
reference; no pickle), ``fig7_F.png``, ``fig8_paths.png`` and ``fig9_errors.png``.
"""

from __future__ import annotations

import sys

from paper import common
from wmrjax.cli import options


def run(
    out,
    dt: float = 0.01,
    t_final: float = 10.0,
    n_empirical: int = 4096,
    n_directions: int = 128,
    n_starts: int = 16,
    progress=None,
) -> dict:
    say = progress or (lambda msg: print(msg, flush=True))
    common.enable_x64()
    import numpy as np

    import wmrjax as w

    ctrl, params, z0, zeta0 = common.section_6_1_setup()
    n_steps = int(round(t_final / dt))
    say("compiling and running the section 6.1 closed loop")
    traj = w.simulate(ctrl, z0, params, dt=dt, n_steps=n_steps)
    t = np.asarray(traj.t)
    state = np.asarray(traj.state)
    control = np.asarray(traj.control)
    ref_post, zref, err, exact = (np.asarray(x) for x in _along_run(ctrl, params, traj.t, traj.state))
    eta1 = control[:, 0]
    eta1_ref = zref[:, 3]  # chi1_ref = eta1_ref for e = 0
    pos_err = np.hypot(state[:, 0] - ref_post[:, 0], state[:, 1] - ref_post[:, 1])
    resid = float(np.max(np.abs(err - exact)))
    summary = _summary(z0, zeta0, ref_post, zref, dt, t, state, eta1, pos_err, resid, traj.diagnostics)
    summary["lemma2"], cert = _lemma2_block(
        ctrl, params, z0, t_final, dt, n_empirical, n_directions=n_directions, n_starts=n_starts, log=say
    )
    say("writing figures")
    out.mkdir(parents=True, exist_ok=True)
    _fig7(out, cert, summary["lemma2"])
    common.write_npz(
        out / "trajectories.npz",
        t=t,
        state=state,
        control=control,
        reference=ref_post,
        state_names=np.array(ctrl.state_names),
        control_names=np.array(["eta1", "eta2"]),
    )
    _figures(out, t, state, ref_post, eta1, eta1_ref)
    common.write_json(out / "summary.json", summary)
    return summary


def _along_run(ctrl, params, t, state):
    """Along a run (times ``t`` (T,), states (T, n)): the reference's posture (T, 3) and law state
    (T, n), the tracking error (T, r m) and the error of the linear dynamics from its first value,
    e^{A t} e(0) (T, r m). One compiled program (cached per closed loop, the parameters an
    argument): evaluated op by op, these compiled one small program per operation and shape (the
    benchmarks page, "Small programs of a cold start", has the count and the time)."""
    import jax

    return jax.jit(_along, static_argnums=0)(ctrl, params, t, state)


def _along(ctrl, params, t, state):
    import jax

    ref_post = jax.vmap(params.reference.posture)(t)
    zref = jax.vmap(lambda s: ctrl.reference_state(s, params))(t)
    err = jax.vmap(lambda s, z: ctrl.error(s, z, params))(t, state).reshape(t.shape[0], -1)
    A = ctrl.error_matrix(params.gains)
    exact = jax.vmap(lambda s: jax.scipy.linalg.expm(A * s) @ err[0])(t)
    return ref_post, zref, err, exact


def _summary(z0, zeta0, ref_post, zref, dt, t, state, eta1, pos_err, resid, d) -> dict:
    """summary.json without the lemma2 block, from the closed-loop run."""
    import numpy as np

    i_min = int(np.argmin(np.abs(eta1)))
    return {
        "experiment": "section_6_1",
        "paper": "d'Andrea-Novel, Campion & Bastin, IJRR 14(6) 1995, section 6.1",
        "robot": "(2,0)",
        "controller": "dynamic feedback linearization, velocity level (Table 4, eq 39)",
        "geometry": {"e": 0.0},
        "reference": "eq (62): x_ref = y_ref = sqrt(2) 1e-2 / 3 (10 - 2t)^3 - sqrt(2)/2 t + 5 sqrt(2)/6",
        "gains": {"poles_per_axis": [-1.0, -1.0], "k1": 2.0, "k0": 1.0},
        "initial_state": {
            "x": float(z0[0]),
            "y": float(z0[1]),
            "theta": float(z0[2]),
            "chi1": float(z0[3]),
            "xdot": float(zeta0[1, 0]),
            "ydot": float(zeta0[1, 1]),
        },
        "reference_initial_state": {
            "x": float(ref_post[0, 0]),
            "y": float(ref_post[0, 1]),
            "theta": float(ref_post[0, 2]),
            "chi1": float(zref[0, 3]),
        },
        "simulation": {
            "integrator": "RK4, fixed step",
            "dt": dt,
            "t_final": float(t[-1]),
            "min_eta1": float(eta1[i_min]),
            "t_min_eta1": float(t[i_min]),
            "max_position_error": float(pos_err.max()),
            "final_position_error": float(pos_err[-1]),
            "final_heading_error": float(np.angle(np.exp(1j * (state[-1, 2] - ref_post[-1, 2])))),
            "max_linear_error_residual": resid,
            "max_linear_error_residual_definition": "max over t and components of |zeta_err(t) - expm(A t) zeta_err(0)|, zeta_err = Psi(X_e) - zeta_ref",
            "min_margin_abs_det_K": float(d.min_margin),
            "failed": bool(d.failed),
        },
    }


def _lemma2_block(ctrl, params, z0, t_final, dt, n_empirical, eps=1e-2, n_directions=128, n_starts=16, log=print):
    """Lemma 2 with the paper's K2 (64), the automatic Lyapunov K2 and the exact ||e^{At}||; the
    exact-map radii; empirical checks and the falsifier (:func:`wmrjax.certify.analyse`)."""
    import jax.numpy as jnp

    from wmrjax import certify as C

    e0 = float(jnp.linalg.norm(ctrl.error(0.0, z0, params)))
    report = C.analyse(
        ctrl,
        params,
        t_final=t_final,
        eps=eps,
        dt=dt,
        n_empirical=n_empirical,
        n_directions=n_directions,
        n_starts=n_starts,
        zeta0_norm=e0,
        log=log,
    )
    block = report.summary()
    block["k2_paper"] = "eq (64)"
    block["lyapunov_K1_r1"] = [float(x) for x in C.lyapunov_bound(ctrl.error_matrix(params.gains))[:2]]
    return block, report.lemma2.certificates()


def _fig7(out, cert, block):
    import numpy as np

    plt = common.pyplot()
    fig, ax = plt.subplots(figsize=(6.5, 4.2))
    for name, lab, c in [
        ("paper", "F(t), K2 of eq (64)", "k"),
        ("lyapunov", "F(t), Lyapunov K2", "C0"),
        ("exact_norm", "F(t), K2 = ||exp(At)||", "C3"),
    ]:
        cc = cert[name]
        ax.plot(np.asarray(cc.ts), np.asarray(cc.F), color=c, lw=1.6 if name == "paper" else 1.2, label=lab)
        ax.plot(float(cc.argmin), float(cc.radius), "o", color=c, ms=4)
    ax.axhline(block["zeta0_norm"], color="C2", ls="--", lw=1.0, label="||zeta_err(0)|| of (63)")
    for key, lab, c in [
        ("radius_exact_map", "exact-map radius (full)", "C4"),
        ("radius_exact_map_position_slice", "exact-map radius (position slice)", "C5"),
    ]:
        if block.get(key) is not None:
            ax.axhline(block[key], color=c, ls=":", lw=1.2, label=f"{lab}: {block[key]:.3g}")
    ax.set_yscale("log")
    ax.set_xlabel("t [s]")
    ax.set_ylabel("F(t) = (M1(t) - eps) / K2(t)  [m, m/s]")
    ax.set_title("Fig. 7: the function F(t) (eps = 0.01)")
    ax.grid(alpha=0.3, which="both")
    ax.legend(fontsize=8)
    common.save_figure(fig, out / "fig7_F.png")
    plt.close(fig)


def _figures(out, t, state, ref, eta1, eta1_ref):
    plt = common.pyplot()
    fig, ax = plt.subplots(figsize=(5.5, 5.5))
    ax.plot(ref[:, 0], ref[:, 1], "k--", lw=1.2, label="reference (62)")
    ax.plot(state[:, 0], state[:, 1], "C0", lw=1.6, label="robot")
    ax.plot(state[0, 0], state[0, 1], "C0o", ms=5)
    ax.plot(ref[0, 0], ref[0, 1], "ko", ms=4)
    ax.set_xlabel("x [m]")
    ax.set_ylabel("y [m]")
    ax.set_title("Fig. 8: reference and robot trajectories")
    ax.axis("equal")
    ax.grid(alpha=0.3)
    ax.legend()
    common.save_figure(fig, out / "fig8_paths.png")
    plt.close(fig)

    fig, axs = plt.subplots(3, 1, figsize=(6.5, 6.5), sharex=True)
    for a, y, lab in zip(
        axs,
        [state[:, 0] - ref[:, 0], state[:, 1] - ref[:, 1], eta1 - eta1_ref],
        ["x - x_ref [m]", "y - y_ref [m]", "eta1 - eta1_ref [m/s]"],
    ):
        a.plot(t, y)
        a.axhline(0.0, color="k", lw=0.6)
        a.set_ylabel(lab)
        a.grid(alpha=0.3)
    axs[-1].set_xlabel("t [s]")
    axs[0].set_title("Fig. 9: errors in x, y and eta1")
    common.save_figure(fig, out / "fig9_errors.png")
    plt.close(fig)


def main(argv=None) -> int:
    from wmrjax.cli import machine, running

    p = options.parser(__doc__.splitlines()[0], "results/section_6_1")
    p.add_argument("--dt", type=options.positive, default=0.01, help="RK4 step [s]")
    p.add_argument("--t-final", type=options.positive, default=10.0, help="horizon [s]")
    a = p.parse_args(argv)
    machine.configure_xla()  # before JAX starts its backend
    machine.check_horizon(p, t_final=a.t_final, dt=a.dt, batch=4096)
    s = running.work(p, a, lambda progress: run(a.out, a.dt, a.t_final, progress=progress))
    sim = s["simulation"]
    print(
        f"section 6.1: min eta1 = {sim['min_eta1']:.4f} m/s at t = {sim['t_min_eta1']:.2f} s; "
        f"position error max {sim['max_position_error']:.4f} m, final {sim['final_position_error']:.2e} m; "
        f"linear-error residual {sim['max_linear_error_residual']:.2e}"
    )
    l2 = s["lemma2"]
    print(
        f"lemma 2 (eps = {l2['eps']}): |zeta_err(0)| = {l2['zeta0_norm']:.4f}; certified radius paper {l2['radius_paper']:.4f} "
        f"(condition 52: {l2['condition_52']}), Lyapunov {l2['radius_lyapunov']:.4f}, exact norm {l2['radius_exact_norm']:.4f}; "
        f"exact map {l2['radius_exact_map']:.4f} (position slice {l2['radius_exact_map_position_slice']:.4f}, "
        f"empirical {l2['empirical_radius_position_slice']}); falsified full {l2['falsified_full']['radius']}, "
        f"position slice {l2['falsified_position_slice']['radius']}"
    )
    print(f"wrote {a.out}/summary.json, trajectories.npz, fig7_F.png, fig8_paths.png, fig9_errors.png")
    return 0


if __name__ == "__main__":
    sys.exit(main())
