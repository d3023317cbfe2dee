r"""Tune the linearizing controller's gains by gradient descent through the simulator, against
random search and CMA-ES on the same terms.

    python -m tuning --out results/tuning                               # problem section_6_1
    python -m tuning --problem car_schedule --out results/car_schedule
    python -m tuning --problem torque_2_1 --out results/torque_2_1

Problems (:mod:`tuning.problems`): ``section_6_1`` (default) -- the §6.1 robot ((2,0), e = 0,
reference (62), dynamic law at velocity level) from initial conditions around (63), 20 Hz
zero-order hold, saturation |eta1| <= 5.5 m/s, |eta2| <= 1 rad/s, +-10 % mismatch, sensor noise,
(omega, zeta) shared by both outputs; ``car_schedule`` -- the (1,1) car with a 24-parameter
gain schedule on random references; ``torque_2_1`` -- type (2,1) at torque level with outer
and inner (Lemma 1) gains, feeding back measured wheel velocities. Any option below overrides
the problem's setting.

Writes ``summary.json``, ``history.json``, ``checkpoint.json`` (a killed run resumes from it),
``loss.png`` (loss vs rollouts, all three methods), ``schedule.png`` (the gains over time) and
``trajectories.png`` (tracking before/after).
"""

from __future__ import annotations

import argparse
import dataclasses
import functools
import sys
import time
from concurrent.futures import ThreadPoolExecutor
from pathlib import Path

from wmrjax import io


def parser():
    from tuning.losses import LossWeights
    from tuning.loop import LEVELS, REFERENCES
    from tuning.problems import PROBLEMS
    from wmrjax import cli

    p = cli.parser(__doc__.splitlines()[0], "results/tuning")
    p.add_argument("--problem", default="section_6_1", choices=sorted(PROBLEMS),
                   help="named problem (tuning.problems); the options below override its settings")
    S = "(default: the problem's)"
    p.add_argument("--robot", default=None, help=f"robot type: (3,0), (2,0), (2,1), (1,1) or (1,2) {S}")
    p.add_argument("--task", default=None, choices=["posture", "point"],
                   help=f"posture: dynamic law (restricted types) or Prop 3 (3,0); point: static Table 3 law {S}")
    p.add_argument("--level", default=None, choices=LEVELS, help=f"velocity (model 5) or torque (Lemma 1) {S}")
    p.add_argument("--reference", default=None, choices=REFERENCES, help=f"reference family {S}")
    p.add_argument("--heading-offset", type=cli.finite, default=None, help=f"reference heading offset [rad] {S}")
    p.add_argument("--geometry", type=cli.finite, nargs=3, default=None, metavar=("L", "E", "DELTA"),
                   help=f"nominal geometry the controller uses [m, m, rad] {S}")
    p.add_argument("--n-train", type=cli.count, default=None, help=f"training scenarios per step {S}")
    p.add_argument("--n-validation", type=cli.count, default=None,
                   help=f"validation scenarios (early stopping, selection) {S}")
    p.add_argument("--n-heldout", type=cli.count, default=None, help=f"held-out scenarios (reported only) {S}")
    p.add_argument("--steps", type=cli.count, default=None, help=f"optimizer steps {S}")
    p.add_argument("--learning-rate", type=cli.positive, default=None,
                   help=f"Adam learning rate (on the softplus-unconstrained parameters) {S}")
    p.add_argument("--poles-init", type=cli.positive, default=None,
                   help=f"initial pole magnitude [1/s] (the paper's: 1) {S}")
    p.add_argument("--per-axis", action="store_true", default=None, help="one set of gains per output")
    p.add_argument("--resample", action=argparse.BooleanOptionalAction, default=None,
                   help=f"fresh training scenarios every gradient step (stochastic gradient) {S}")
    p.add_argument("--knots", type=cli.nonnegative_int, default=None,
                   help=f"gain schedule with this many knots uniform on [0, t_final] (0: constant gains) {S}")
    p.add_argument("--knot-times", type=cli.nonnegative, nargs="+", default=None,
                   help="explicit knot times of the gain schedule [s] (overrides --knots)")
    p.add_argument("--min-damping", type=cli.nonnegative, default=None,
                   help=f"floor of every damping zeta (in [0, 1)) {S}")
    p.add_argument("--parameterization", default=None, choices=["damping", "poles"],
                   help=f"damping: (omega, zeta) factors (real or complex poles); poles: real poles only {S}")
    p.add_argument("--mismatch", type=cli.fraction, default=None,
                   help=f"+- relative input-scale/geometry error of the plant (in [0, 1)) {S}")
    p.add_argument("--input-limit", type=cli.limit, nargs="*", default=None,
                   help="plant actuator limits per input [m/s, rad/s; per s^2 at torque level] (inf: none; no "
                        f"values: no saturation) {S}")
    p.add_argument("--noise-std", type=cli.nonnegative, nargs="*", default=None,
                   help=f"measurement noise std of x, y [m] and theta [rad] (and steering angles [rad]) {S}")
    p.add_argument("--control-dt", type=cli.positive, default=None, help=f"controller period (zero-order hold) [s] {S}")
    p.add_argument("--t-final", type=cli.positive, default=None, help=f"horizon of every scenario [s] {S}")
    for f in LossWeights._fields:
        p.add_argument(f"--w-{f}", type=cli.nonnegative, default=None, help=f"weight of the {f} loss term (>= 0) {S}")
    p.add_argument("--baseline-seeds", type=cli.count, default=None, help=f"seeds of each baseline {S}")
    p.add_argument("--baseline-budget", type=cli.positive, default=None,
                   help=f"baseline rollouts as a multiple of the gradient's {S}")
    p.add_argument("--cma-population", type=cli.nonnegative_int, default=None,
                   help=f"CMA-ES population (0: 4 + floor(3 ln n)) {S}")
    p.add_argument("--seed", type=cli.seed, default=None, help=f"PRNG seed of the scenarios (and the baselines) {S}")
    p.add_argument("--fresh", action="store_true", help="ignore (delete) an existing checkpoint in --out")
    return p


_FIELDS = {"robot": "robot", "task": "task", "level": "level", "reference": "reference",
           "heading_offset": "heading_offset", "n_train": "n_train", "n_validation": "n_validation",
           "n_heldout": "n_heldout", "steps": "steps", "learning_rate": "learning_rate", "poles_init": "poles_init",
           "knots": "knots", "parameterization": "parameterization", "mismatch": "mismatch",
           "control_dt": "control_dt", "t_final": "t_final", "baseline_seeds": "baseline_seeds",
           "baseline_budget": "baseline_budget", "cma_population": "cma_population", "seed": "seed",
           "min_damping": "min_damping"}


def config_from_args(a):
    """The problem's :class:`tuning.TuneConfig` with every option given on the command line applied."""
    from tuning.losses import LossWeights
    from tuning.problems import PROBLEMS, preset

    over = {f: getattr(a, k) for k, f in _FIELDS.items() if getattr(a, k) is not None}
    for k in ("geometry", "input_limit", "noise_std", "knot_times"):
        if getattr(a, k) is not None:
            over[k] = tuple(getattr(a, k))
    if a.per_axis:
        over["shared"] = False
    if a.resample is not None:
        over["resample"] = a.resample
    given = {f: getattr(a, f"w_{f}") for f in LossWeights._fields if getattr(a, f"w_{f}") is not None}
    if given:
        base = LossWeights(*PROBLEMS[a.problem].get("weights", tuple(LossWeights())))
        over["weights"] = tuple(base._replace(**given))
    return preset(a.problem, **over)


def run(cfg, out: Path, fresh: bool = False, log=print, progress=None) -> dict:
    """Tune, evaluate, run the baselines, write the figures and ``summary.json``; returns the summary."""
    import jax

    jax.config.update("jax_enable_x64", True)   # this entry point runs in float64
    import jax.numpy as jnp
    import numpy as np

    from tuning import baselines, loop

    say = progress or log
    out.mkdir(parents=True, exist_ok=True)
    if fresh and (out / "checkpoint.json").exists():
        (out / "checkpoint.json").unlink()
    t0 = time.perf_counter()
    say(f"problem {cfg.problem}: building scenarios; compiling the batched rollout and its gradient (first step)")
    programs = {}
    second = ThreadPoolExecutor(max_workers=1)

    def prepare(built):
        # the programs of the validation, the evaluations and the figure, compiled on a second
        # thread while this one compiles the gradient (XLA compiles without the GIL); tracing
        # the validation program here first traces the controller period that every program
        # shares, once, instead of on both threads at the same time
        loop.validation_value.trace(built["spec"].init(cfg.poles_init), built["validation"], built["ctrl"],
                                    built["spec"], built["geometry"], built["rcfg"], built["w_arr"])
        programs.update(_programs(built))
        programs["ready"] = [second.submit(_warm_up, programs, built, cfg.poles_init), second.submit(_preload)]

    try:
        res = loop.tune(cfg, out, log=log, on_built=prepare)
        for done in programs["ready"]:
            done.result()                   # their errors are raised here
    except BaseException:
        second.shutdown(wait=False, cancel_futures=True)    # a failed run does not wait for them
        raise
    second.shutdown()
    grad_wall = time.perf_counter() - t0
    ctrl, spec, g, rcfg, train, heldout = (res[k] for k in ("ctrl", "spec", "geometry", "rcfg", "train", "heldout"))
    st = res["state"]
    paper_raw = spec.init(cfg.poles_init)
    tuned_raw = jnp.asarray(res["best_raw"])
    evaluate_on = programs["evaluate_on"]
    train_eval = functools.partial(evaluate_on, scenarios=train)
    heldout_eval = functools.partial(evaluate_on, scenarios=heldout)

    say("evaluating the paper's and the tuned gains on the held-out scenarios")
    tr_paper, tr_tuned = (float(v) for v in train_eval(np.stack([np.asarray(paper_raw), np.asarray(tuned_raw)])))
    ho, (ho_ok, ho_m) = heldout_eval(np.stack([np.asarray(paper_raw), np.asarray(tuned_raw)]), with_aux=True)
    ho_paper, ho_tuned = (float(v) for v in ho)        # +inf where a set's objective is not finite
    m_paper, m_tuned = (jax.tree_util.tree_map(lambda x: x[i], ho_m) for i in (0, 1))
    sing_paper, sing_tuned = (int(np.sum(ho_m.singular[i])) for i in (0, 1))
    fail_paper, fail_tuned = (int(np.sum(~ho_ok[i])) for i in (0, 1))
    log(f"held-out loss: paper gains {ho_paper:.5g}, tuned {ho_tuned:.5g} (ratio {ho_paper / ho_tuned:.2f}); "
        f"singular events {sing_paper} -> {sing_tuned}")

    hist = st["history"]
    budget = cfg.baseline_rollouts()
    pop = cfg.population(spec.size)
    runs = {"random_search": [], "cma_es": []}
    t_base = {"random_search": 0.0, "cma_es": 0.0}
    for k in range(cfg.baseline_seeds):
        seed = cfg.seed * 1000 + k
        say(f"baselines, seed {k + 1}/{cfg.baseline_seeds}: random search and CMA-ES, {budget} rollouts each")
        t1 = time.perf_counter()
        runs["random_search"].append(baselines.random_search(
            spec, train_eval, paper_raw, budget_rollouts=budget, n_train=cfg.n_train, seed=seed,
            low=cfg.search_low, high=cfg.search_high))
        t2 = time.perf_counter()
        runs["cma_es"].append(baselines.cma_es(spec, train_eval, paper_raw, budget_rollouts=budget,
                                               n_train=cfg.n_train, seed=seed, population=pop, sigma=cfg.cma_sigma))
        t_base["random_search"] += t2 - t1
        t_base["cma_es"] += time.perf_counter() - t2
    base = {}
    match = {}
    for name, rs in runs.items():
        held = heldout_eval(np.stack([np.asarray(r.best_raw) for r in rs]))
        reach = [baselines.rollouts_to_reach(hist, r.best_loss) for r in rs]
        base[name] = {
            "best_loss": float(np.median([r.best_loss for r in rs])),
            "best_heldout_loss": float(np.median(held)),
            "rollouts_to_best": float(np.median([r.rollouts_to_best for r in rs])),
            "statistic": f"median over {len(rs)} seeds",
            "per_seed": [{"seed": r.seed, "best_loss": r.best_loss, "best_heldout_loss": float(h),
                          "rollouts_to_best": r.rollouts_to_best, "rollouts": r.rollouts,
                          "gradient_rollouts_to_match": m}
                         for r, h, m in zip(rs, held, reach)],
            "rollouts_budget": budget, "wall_time_s": t_base[name],
        }
        met = [m for m in reach if m is not None]
        med = float(np.median([np.inf if m is None else m for m in reach]))    # a seed never matched counts as inf
        match[name] = med if np.isfinite(med) else None
        ratio = float(np.median([r.rollouts_to_best / m if m is not None else 0.0 for r, m in zip(rs, reach)]))
        base[name]["rollout_ratio_baseline_over_gradient"] = ratio if match[name] is not None else None
        base[name]["seeds_matched_by_gradient"] = len(met)
        log(f"{name}: median best train loss {base[name]['best_loss']:.5g} after {base[name]['rollouts_to_best']:.0f} "
            f"rollouts, held-out {base[name]['best_heldout_loss']:.5g}; gradient reached it after {match[name]} "
            f"rollouts ({len(met)}/{len(reach)} seeds)")
    base["cma_es"]["population"] = pop
    base["cma_es"]["sigma0"] = cfg.cma_sigma
    base["cma_es"]["implementation"] = "cmaes (CyberAgent) CMA, ask/tell; candidates simulated in batched jit calls"
    base["random_search"]["box"] = (f"log-uniform: rates in [{cfg.search_low}, {cfg.search_high}] 1/s, "
                                    f"dampings in [{max(0.3, 1.01 * cfg.min_damping):g}, 3], every knot independently")

    radius = None
    cert = loop.certificate_setup(ctrl, cfg.reference, g, cfg.t_final)
    if cert is not None:
        from tuning.losses import certificate_radius

        radius_of = jax.jit(lambda r: certificate_radius(spec.gains(r), cert[1], cert[0], cert[2]),
                            compiler_options=loop.QUICK_COMPILE)
        radius = {k: float(radius_of(r)) for k, r in (("paper_gains", paper_raw), ("tuned", tuned_raw))}
    summary = {
        "experiment": "tuning", "problem": cfg.problem, "config": dataclasses.asdict(cfg),
        "controller": f"{type(ctrl).__name__} of type {ctrl.robot.name}, {ctrl.level} level",
        "n_parameters": spec.size,
        "gain_family": ("gain schedule, knots at " + ", ".join(f"{t:g}" for t in spec.knots) + " s"
                        if spec.knots else "constant") + (", shared by the outputs" if spec.shared else ", per output"),
        "initial_gains": _gains_report(spec, paper_raw),
        "tuned_gains": {**_gains_report(spec, tuned_raw), "selected_by": "best validation loss among evaluations"},
        "train_loss": {"initial": hist[0]["train_loss"], "final": hist[-1]["train_loss"],
                       "paper_gains": tr_paper, "tuned": tr_tuned},
        "heldout_loss": {"paper_gains": ho_paper, "tuned": ho_tuned,        # null ratio where one is not finite
                         "ratio_paper_over_tuned": ho_paper / ho_tuned if np.isfinite([ho_paper, ho_tuned]).all()
                         else None},
        "heldout_terms": {k: {f: float(np.mean(np.asarray(getattr(m, f))[np.asarray(m.valid)]))
                              for f in ("tracking", "effort", "saturation", "barrier")}
                          for k, m in (("paper_gains", m_paper), ("tuned", m_tuned))},
        "singularity_events": {"paper_gains": sing_paper, "tuned": sing_tuned},
        "failed_heldout_scenarios": {"paper_gains": fail_paper, "tuned": fail_tuned},
        "excluded_training_scenarios": st["excluded"],
        "rollouts": st["rollouts"],
        "rollout_counting": "one rollout = one scenario simulated once; a gradient step over B scenarios counts B "
                            "(its extra cost is in gradient_wall_time_s); held-out and validation runs are not counted",
        "objective": f"mean loss of the valid scenarios + {loop.FAILURE_PENALTY} x fraction failed (+ certificate term)",
        "baselines": base,
        "rollouts_to_match": match,
        "steps": len(hist), "stopped_early": st["stopped_early"],
        "gradient_wall_time_s": grad_wall, "tuning_wall_time_s_including_compile": st["wall_time_s"],
        "certified_radius": radius,
    }
    say("writing history, figures and summary")
    io.write_json(out / "history.json", {"gradient": hist, **{
        name: [{"seed": r.seed, "best_so_far": r.best_so_far, "rollouts_per_candidate": r.rollouts_per_candidate}
               for r in rs] for name, rs in runs.items()}})
    _figures(out, cfg, res, hist, runs, paper_raw, tuned_raw, programs)
    summary["wall_time_s"] = time.perf_counter() - t0
    io.write_json(out / "summary.json", summary)
    return summary


def _programs(built) -> dict:
    """The functions of a run after its gradient loop.

    Returns:
      A dict: ``evaluate_on`` (:func:`tuning.baselines.candidate_evaluator` of the training
      objective, with per-scenario validity and metrics as aux: the training-set evaluations,
      the held-out report and the baselines; +inf where an objective is not finite),
      ``trajectories(gains) -> (states (n_periods, n), output errors (n_periods, 2))`` of
      held-out scenario 0, that ``scenario`` (on the host) and its sample times ``t`` [s].
    """
    import jax
    import jax.numpy as jnp
    import numpy as np

    from tuning import baselines, loop
    from tuning.scenarios import rollout

    ctrl, spec, g, rcfg, w_arr, cert_term = (built[k] for k in ("ctrl", "spec", "geometry", "rcfg", "w_arr",
                                                                 "cert_term"))

    def objective(raw, scen):
        val, ok, m = loop.batch_value(raw, scen, ctrl, spec, g, rcfg, w_arr)
        return loop.objective(val, ok) + cert_term(raw), (ok, m)

    sc = jax.tree_util.tree_map(lambda x: np.asarray(x)[0], built["heldout"])     # on the host: no per-leaf program
    t = np.arange(rcfg.n_periods) * rcfg.control_dt
    params = ctrl.params_unchecked(sc.reference, 1.0, g)

    @functools.partial(jax.jit, compiler_options=loop.QUICK_COMPILE)
    def trajectories(gains):      # the sampled states and their output errors
        _, (zs, _) = rollout(ctrl, gains, g, sc, rcfg, trajectory=True)
        return zs, jax.vmap(lambda tt, z: ctrl.error(tt, z, params)[0])(jnp.asarray(t), zs)

    # one program for every evaluation after the gradient's (the training and held-out sets
    # have the same size in the default problems; a set of another size compiles its own)
    return {"evaluate_on": baselines.candidate_evaluator(objective, spec.shape, compiler_options=loop.LOOP_COMPILE),
            "trajectories": trajectories,
            "scenario": sc, "t": t}


def _warm_up(programs, built, poles_init) -> None:
    """Compile the validation program and ``programs`` by calling each once (an evaluation
    runs one chunk of 16 candidates)."""
    import jax
    import numpy as np

    from tuning import loop

    spec = built["spec"]
    raw = spec.init(poles_init)
    loop.validation_value(raw, built["validation"], built["ctrl"], spec, built["geometry"], built["rcfg"],
                          built["w_arr"])
    programs["evaluate_on"](np.asarray(raw)[None], built["train"])
    if jax.tree_util.tree_leaves(built["heldout"])[0].shape[0] != jax.tree_util.tree_leaves(built["train"])[0].shape[0]:
        programs["evaluate_on"](np.asarray(raw)[None], built["heldout"])      # a set of another size: its own program
    programs["trajectories"](spec.gains(raw))


def _preload() -> None:
    """Import what the end of a run needs (cmaes imports scipy.stats, 0.5 s; matplotlib 0.5 s)
    on the second thread, while the main one runs the gradient loop."""
    import cmaes  # noqa: F401

    io.headless_pyplot()


def _gains_report(spec, raw):
    import numpy as np

    pos = np.asarray(spec.positive(raw))
    params = (dict(zip(spec.names(), pos.tolist())) if spec.shared and not spec.knots else pos.tolist())
    return {"parameterization": spec.parameterization, "shared_across_outputs": spec.shared,
            "knots_s": list(spec.knots), "parameter_names": spec.names(), "parameters": params,
            "coefficients_k0_to_kr-1": np.asarray(spec.coefficients(raw)).tolist(),
            "closed_loop_poles_re_im": spec.closed_loop_poles(raw)}


def _band(runs):
    """(rollouts, median, low, high) of the best-so-far curves of several seeds."""
    import numpy as np

    n = min(len(r.best_so_far) for r in runs)
    curves = np.stack([np.asarray(r.best_so_far[:n]) for r in runs])
    x = (np.arange(n) + 1) * runs[0].rollouts_per_candidate
    return x, np.median(curves, axis=0), curves.min(axis=0), curves.max(axis=0)


def _figures(out, cfg, res, hist, runs, paper_raw, tuned_raw, programs):
    import jax
    import jax.numpy as jnp
    import numpy as np

    plt = io.headless_pyplot()
    fig, ax = plt.subplots(figsize=(6.8, 4.3))
    ax.semilogy([h["rollouts"] for h in hist], [h["train_loss"] for h in hist], "C0", label="gradient (train)")
    va = [(h["rollouts"], h["validation_loss"]) for h in hist if "validation_loss" in h]
    ax.semilogy(*zip(*va), "C0o--", ms=3, label="gradient (validation)")
    for (name, rs), c in zip(runs.items(), ("C3", "C2")):
        x, med, lo, hi = _band(rs)
        ax.semilogy(x, med, c, label=f"{name.replace('_', ' ')} (best so far, median of {len(rs)} seeds)")
        ax.fill_between(x, lo, hi, color=c, alpha=0.2, lw=0)
    ax.set_xscale("log")
    ax.set_xlabel("rollouts (scenario simulations)")
    ax.set_ylabel("training objective")
    ax.set_title(f"{cfg.problem}: loss vs rollouts (band: min-max over seeds)")
    ax.grid(alpha=0.3, which="both")
    ax.legend(fontsize=7)
    io.write_png(fig, out / "loss.png")
    plt.close(fig)

    spec = res["spec"]
    ts = np.linspace(0.0, cfg.t_final, 201)
    fig, axs = plt.subplots(1, spec.r, figsize=(3.6 * spec.r, 3.4), squeeze=False)
    names = spec.names()
    # one program for both schedules (a jit per schedule compiled twice)
    schedule_at = jax.jit(lambda gains, ts: jax.vmap(gains.parameters_at)(ts))
    for raw, lab, ls in ((paper_raw, "paper", "--"), (tuned_raw, "tuned", "-")):
        gains = spec.gains(raw)
        if spec.knots:
            pos = np.asarray(schedule_at(gains, jnp.asarray(ts)))                            # (T, m, r)
        else:                                                                             # (T, 1 or m, r)
            one = np.asarray(spec.positive(raw)).reshape(-1, spec.r)
            pos = np.broadcast_to(one, (len(ts),) + one.shape)
        for j in range(spec.r):
            for i in range(pos.shape[1]):
                axs[0, j].plot(ts, pos[:, i, j], f"C{i}{ls}", lw=1.2, label=f"{lab}, output {i + 1}")
    for j in range(spec.r):
        unit = "" if names[j].startswith("zeta") else " [1/s]"
        axs[0, j].set_title(names[j] + unit)
        axs[0, j].set_xlabel("t [s]")
        axs[0, j].grid(alpha=0.3)
        if spec.knots:
            for tk in spec.knots:
                axs[0, j].axvline(tk, color="0.7", lw=0.6)
    axs[0, 0].legend(fontsize=6)
    fig.suptitle(f"{cfg.problem}: gains over time (grey: knots)" if spec.knots else f"{cfg.problem}: gains")
    fig.tight_layout()
    io.write_png(fig, out / "schedule.png")
    plt.close(fig)

    sc, t = programs["scenario"], programs["t"]
    fig, axs = plt.subplots(1, 2, figsize=(11, 4.4))
    ref = np.asarray(jax.jit(jax.vmap(sc.reference.position))(t))
    axs[0].plot(ref[:, 0], ref[:, 1], "k--", lw=1.2, label="reference")
    for raw, lab, c in ((paper_raw, "paper gains (poles -1)", "C3"), (tuned_raw, "tuned", "C0")):
        zs, err = (np.asarray(x) for x in programs["trajectories"](spec.gains(raw)))
        axs[0].plot(zs[:, 0], zs[:, 1], c, lw=1.2, label=lab)
        axs[1].semilogy(t, np.maximum(np.hypot(err[:, 0], err[:, 1]), 1e-8), c, label=lab)
    axs[0].set_xlabel("x [m]")
    axs[0].set_ylabel("y [m]")
    axs[0].axis("equal")
    axs[0].set_title(f"{cfg.problem}: one held-out scenario (saturation, mismatch, noise)")
    axs[1].set_xlabel("t [s]")
    axs[1].set_ylabel("output position error [m]")
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
    import jax

    jax.config.update("jax_enable_x64", True)   # float64 from the first check on (run() sets it too)
    try:
        cfg = config_from_args(a)
        from tuning.loop import validate

        validate(cfg)
    except ValueError as e:
        p.error(str(e))
    s = cli.work(p, a, lambda progress: run(cfg, a.out, a.fresh, log=progress),
                 hint=lambda msg: msg + "; or rerun with --fresh to start over" if "checkpoint" in msg else msg)
    b = s["baselines"]
    print(f"{cfg.problem}: {s['n_parameters']} parameters; held-out loss paper {s['heldout_loss']['paper_gains']:.4g} "
          f"-> tuned {s['heldout_loss']['tuned']:.4g} (CMA-ES {b['cma_es']['best_heldout_loss']:.4g}, random search "
          f"{b['random_search']['best_heldout_loss']:.4g}); singular events {s['singularity_events']}; "
          f"gradient rollouts {s['rollouts']}, to match CMA-ES {s['rollouts_to_match']['cma_es']} (CMA-ES best after "
          f"{b['cma_es']['rollouts_to_best']:.0f}); {s['wall_time_s']:.1f} s")
    print(f"wrote {a.out}/summary.json, history.json, checkpoint.json, loss.png, schedule.png, trajectories.png")
    return 0


if __name__ == "__main__":
    sys.exit(main())
