r"""Tune the linearizing controller's poles by gradient descent through the simulator.

    python -m tuning --out results/tuning

Default case: the §6.1 robot ((2,0), e = 0, reference (62), dynamic linearization at velocity
level) from initial conditions around (63) (+-0.5 m, +-0.5 m/s), with a 20 Hz zero-order-hold
controller, actuator saturation |eta1| <= 5.5 m/s, |eta2| <= 1 rad/s, +-10 % input-scale and
geometry mismatch, and sensor noise (1 cm, 0.005 rad). Writes ``summary.json``,
``history.json``, ``checkpoint.json`` (a killed run resumes from it), ``loss.png`` and
``trajectories.png``.
"""

from __future__ import annotations

import dataclasses
import sys
import time
from pathlib import Path

from wmrjax import io


def parser():
    from tuning.losses import LossWeights
    from tuning.loop import REFERENCES, TuneConfig
    from wmrjax import cli

    d = TuneConfig()
    p = cli.parser(__doc__.splitlines()[0], "results/tuning")
    p.add_argument("--robot", default=d.robot, help="robot type: (3,0), (2,0), (2,1), (1,1) or (1,2)")
    p.add_argument("--task", default=d.task, choices=["posture", "point"],
                   help="posture: dynamic law (restricted types) or Prop 3 (3,0); point: static Table 3 law")
    p.add_argument("--reference", default=d.reference, choices=REFERENCES, help="reference family")
    p.add_argument("--geometry", type=cli.finite, nargs=3, default=list(d.geometry), metavar=("L", "E", "DELTA"),
                   help="nominal geometry the controller uses [m, m, rad]")
    p.add_argument("--n-train", type=cli.count, default=d.n_train, help="training scenarios per step")
    p.add_argument("--n-heldout", type=cli.count, default=d.n_heldout, help="held-out scenarios")
    p.add_argument("--steps", type=cli.count, default=d.steps, help="optimizer steps")
    p.add_argument("--learning-rate", type=cli.positive, default=d.learning_rate,
                   help="Adam learning rate (on the softplus-unconstrained parameters)")
    p.add_argument("--poles-init", type=cli.positive, default=d.poles_init,
                   help="initial pole magnitude [1/s] (the paper's: 1)")
    p.add_argument("--per-axis", action="store_true", help="one set of poles per output instead of shared")
    p.add_argument("--parameterization", default=d.parameterization, choices=["damping", "poles"],
                   help="damping: (omega, zeta) factors (real or complex poles); poles: real poles only")
    p.add_argument("--mismatch", type=cli.fraction, default=d.mismatch,
                   help="+- relative input-scale/geometry error of the plant (dimensionless, in [0, 1))")
    p.add_argument("--input-limit", type=cli.limit, nargs="*", default=list(d.input_limit),
                   help="plant actuator limits per input [m/s, rad/s] (> 0, inf: none; no values: no saturation)")
    p.add_argument("--noise-std", type=cli.nonnegative, nargs="*", default=list(d.noise_std),
                   help="measurement noise std of x, y [m] and theta [rad] (and steering angles [rad])")
    p.add_argument("--control-dt", type=cli.positive, default=d.control_dt, help="controller period (zero-order hold) [s]")
    p.add_argument("--t-final", type=cli.positive, default=d.t_final, help="horizon of every scenario [s]")
    for f, v in LossWeights()._asdict().items():
        p.add_argument(f"--w-{f}", type=cli.nonnegative, default=v, help=f"weight of the {f} loss term (>= 0)")
    p.add_argument("--seed", type=cli.seed, default=d.seed, help="PRNG seed of the scenarios")
    p.add_argument("--fresh", action="store_true", help="ignore (delete) an existing checkpoint in --out")
    return p


def config_from_args(a):
    from tuning.losses import LossWeights
    from tuning.loop import TuneConfig

    return TuneConfig(robot=a.robot, task=a.task, reference=a.reference, geometry=tuple(a.geometry),
                      n_train=a.n_train, n_heldout=a.n_heldout, steps=a.steps, learning_rate=a.learning_rate,
                      poles_init=a.poles_init, shared=not a.per_axis, parameterization=a.parameterization,
                      mismatch=a.mismatch,
                      input_limit=tuple(a.input_limit), noise_std=tuple(a.noise_std), control_dt=a.control_dt,
                      t_final=a.t_final, seed=a.seed,
                      weights=tuple(LossWeights(*(getattr(a, f"w_{f}") for f in LossWeights._fields)))).check()


def run(cfg, out: Path, fresh: bool = False, log=print, progress=None) -> dict:
    import jax

    jax.config.update("jax_enable_x64", True)   # this entry point runs in float64
    import jax.numpy as jnp
    import numpy as np

    from tuning import loop

    say = progress or log
    out.mkdir(parents=True, exist_ok=True)
    if fresh and (out / "checkpoint.json").exists():
        (out / "checkpoint.json").unlink()
    t0 = time.perf_counter()
    say("building scenarios; compiling the batched rollout and its gradient (first step)")
    res = loop.tune(cfg, out, log=log)
    say("evaluating the paper's and the tuned gains on the held-out scenarios")
    ctrl, spec, g, rcfg, train, heldout, w_arr = (res[k] for k in ("ctrl", "spec", "geometry", "rcfg", "train",
                                                                    "heldout", "w_arr"))
    st = res["state"]
    paper_raw = spec.init(cfg.poles_init)
    tuned_raw = jnp.asarray(res["best_raw"])

    def evaluate(raw, scen):
        val, ok, m = loop.batch_value(raw, scen, ctrl, spec, g, rcfg, w_arr)
        return float(val + res["cert_term"](raw)), int(np.sum(np.asarray(m.singular))), int(np.sum(~np.asarray(ok))), m

    tr_paper, _, _, _ = evaluate(paper_raw, train)
    tr_tuned, _, _, _ = evaluate(tuned_raw, train)
    ho_paper, sing_paper, fail_paper, m_paper = evaluate(paper_raw, heldout)
    ho_tuned, sing_tuned, fail_tuned, m_tuned = evaluate(tuned_raw, heldout)
    log(f"held-out loss: paper gains {ho_paper:.5g}, tuned {ho_tuned:.5g} (ratio {ho_paper / ho_tuned:.2f}); "
        f"singular events {sing_paper} -> {sing_tuned}")
    grad_rollouts = st["rollouts"]
    say(f"random search with the same budget ({grad_rollouts} rollouts)")
    rs = loop.random_search(cfg, ctrl, spec, g, rcfg, train, w_arr, res["cert_term"], grad_rollouts,
                            jax.random.PRNGKey(cfg.seed + 1))
    hist = st["history"]
    match = next((h["rollouts"] for h in hist if h["train_loss"] <= rs["best_loss"]), None)
    log(f"random search: best train loss {rs['best_loss']:.5g} after {rs['rollouts_to_best']} rollouts; "
        f"gradient method matched it after {match} rollouts")
    radius = None
    cert = loop.certificate_setup(ctrl, cfg.reference, g, cfg.t_final)
    if cert is not None:
        from tuning.losses import certificate_radius

        radius = {k: float(certificate_radius(spec.gains(r), cert[1], cert[0], cert[2]))
                  for k, r in (("paper_gains", paper_raw), ("tuned", tuned_raw))}
    summary = {
        "experiment": "tuning", "config": dataclasses.asdict(cfg),
        "controller": f"{type(ctrl).__name__} of type {ctrl.robot.name}, velocity level",
        "initial_gains": _gains_report(spec, paper_raw),
        "tuned_gains": {**_gains_report(spec, tuned_raw), "selected_by": "best held-out loss among evaluations"},
        "train_loss": {"initial": hist[0]["train_loss"], "final": hist[-1]["train_loss"],
                       "paper_gains": tr_paper, "tuned": tr_tuned},
        "heldout_loss": {"paper_gains": ho_paper, "tuned": ho_tuned, "ratio_paper_over_tuned": ho_paper / ho_tuned},
        "heldout_terms": {k: {f: float(np.mean(np.asarray(getattr(m, f))[np.asarray(m.valid)]))
                              for f in ("tracking", "effort", "saturation", "barrier")}
                          for k, m in (("paper_gains", m_paper), ("tuned", m_tuned))},
        "singularity_events": {"paper_gains": sing_paper, "tuned": sing_tuned},
        "failed_heldout_scenarios": {"paper_gains": fail_paper, "tuned": fail_tuned},
        "excluded_training_scenarios": st["excluded"],
        "rollouts": grad_rollouts, "rollout_counting": "a forward+backward pass over B scenarios counts B",
        "rollouts_to_match_baseline": match,
        "steps": len(hist), "stopped_early": st["stopped_early"],
        "wall_time_s": time.perf_counter() - t0, "tuning_wall_time_s_including_compile": st["wall_time_s"],
        "baseline": {k: rs[k] for k in ("name", "best_loss", "rollouts_to_best", "candidates", "best_params", "best_poles")},
        "certified_radius_lyapunov": radius,
    }
    say("writing history, figures and summary")
    io.write_json(out / "history.json", {"gradient": hist, "random_search_best_so_far": rs["best_so_far"],
                                              "random_search_rollouts_per_candidate": rs["rollouts_per_candidate"]})
    _figures(out, cfg, res, hist, rs, paper_raw, tuned_raw)
    io.write_json(out / "summary.json", summary)
    return summary


def _gains_report(spec, raw):
    import numpy as np

    return {"parameterization": spec.parameterization, "shared_across_outputs": spec.shared,
            "parameters": dict(zip(spec.names(), np.asarray(spec.positive(raw)).reshape(-1, spec.r)[0].tolist()))
            if spec.shared else np.asarray(spec.positive(raw)).tolist(),
            "coefficients_k0_to_kr-1": np.asarray(spec.coefficients(raw)).tolist(),
            "closed_loop_poles_re_im": spec.closed_loop_poles(raw)}


def _figures(out, cfg, res, hist, rs, paper_raw, tuned_raw):
    import jax
    import numpy as np

    from tuning.scenarios import rollout

    plt = io.headless_pyplot()
    fig, ax = plt.subplots(figsize=(6.6, 4.2))
    ax.semilogy([h["rollouts"] for h in hist], [h["train_loss"] for h in hist], "C0", label="gradient (train)")
    ho = [(h["rollouts"], h["heldout_loss"]) for h in hist if "heldout_loss" in h]
    ax.semilogy(*zip(*ho), "C0o--", ms=3, label="gradient (held-out)")
    rb = np.asarray(rs["best_so_far"])
    ax.semilogy((np.arange(len(rb)) + 1) * rs["rollouts_per_candidate"], rb, "C3", label="random search (best so far)")
    ax.set_xlabel("rollouts (scenario simulations)")
    ax.set_ylabel("loss")
    ax.set_title("tuning the poles: loss vs rollouts")
    ax.grid(alpha=0.3, which="both")
    ax.legend(fontsize=8)
    io.write_png(fig, out / "loss.png")
    plt.close(fig)

    ctrl, spec, g, rcfg = res["ctrl"], res["spec"], res["geometry"], res["rcfg"]
    sc = jax.tree_util.tree_map(lambda x: x[0], res["heldout"])
    fig, axs = plt.subplots(1, 2, figsize=(11, 4.4))
    t = np.arange(rcfg.n_periods) * rcfg.control_dt
    ref = np.asarray(jax.vmap(sc.reference.position)(t))
    axs[0].plot(ref[:, 0], ref[:, 1], "k--", lw=1.2, label="reference")
    for raw, lab, c in ((paper_raw, "paper gains (poles -1)", "C3"), (tuned_raw, "tuned", "C0")):
        m, (zs, us) = rollout(ctrl, spec.gains(raw), g, sc, rcfg, trajectory=True)
        zs = np.asarray(zs)
        params = ctrl.params_unchecked(sc.reference, 1.0, g)
        err = np.asarray(jax.vmap(lambda tt, z: ctrl.error(tt, z, params)[0])(t, zs))
        axs[0].plot(zs[:, 0], zs[:, 1], c, lw=1.2, label=lab)
        axs[1].semilogy(t, np.maximum(np.hypot(err[:, 0], err[:, 1]), 1e-8), c, label=lab)
    axs[0].set_xlabel("x [m]")
    axs[0].set_ylabel("y [m]")
    axs[0].axis("equal")
    axs[0].set_title("one held-out scenario (saturation, mismatch, noise)")
    axs[1].set_xlabel("t [s]")
    axs[1].set_ylabel("position error [m]")
    for a in axs:
        a.grid(alpha=0.3)
        a.legend(fontsize=8)
    fig.tight_layout()
    io.write_png(fig, out / "trajectories.png")
    plt.close(fig)


def main(argv=None) -> int:
    from wmrjax import cli

    p = parser()
    a = p.parse_args(argv)
    try:
        cfg = config_from_args(a)
        from tuning.loop import validate

        validate(cfg)
    except ValueError as e:
        p.error(str(e))
    s = cli.work(p, a, lambda progress: run(cfg, a.out, a.fresh, log=progress),
                 hint=lambda msg: msg + "; or rerun with --fresh to start over" if "checkpoint" in msg else msg)
    print(f"tuned {s['tuned_gains']['parameters']}; held-out loss paper {s['heldout_loss']['paper_gains']:.4g} -> "
          f"tuned {s['heldout_loss']['tuned']:.4g}; singular events {s['singularity_events']}; "
          f"rollouts {s['rollouts']}, to match random search {s['rollouts_to_match_baseline']} "
          f"(random search best after {s['baseline']['rollouts_to_best']}); {s['wall_time_s']:.1f} s")
    print(f"wrote {a.out}/summary.json, history.json, checkpoint.json, loss.png, trajectories.png")
    return 0


if __name__ == "__main__":
    sys.exit(main())
