r"""Multi-seed study: every problem x method x seed, one table and one figure.

    python -m tuning.study --out results/tuning_study

For each problem of :mod:`tuning.problems` and each seed s (default 5), one run of
``python -m tuning --problem P --seed s --baseline-seeds 1``: the scenarios (training,
validation, held-out) and the baselines' random streams change with s. Each run writes its own
directory ``P/seed_s`` (a killed study resumes: finished runs are kept, an unfinished run
resumes from its checkpoint). The study writes

* ``study.csv`` -- one row per problem x method x seed: held-out loss, best training objective,
  rollouts to that best, gradient rollouts to reach it, singularity events, wall time;
* ``summary.json`` -- per problem and method the median and the spread (min, max) over seeds,
  the target checks of the tuning issue, and the table as Markdown;
* ``study.png`` -- held-out loss per method and seed, the paper's gains for reference.
"""

from __future__ import annotations

import csv
import io as _stdio
import json
import sys
import time
from pathlib import Path

from wmrjax import io

METHODS = ("paper_gains", "gradient", "cma_es", "random_search")


def parser():
    from tuning.problems import PROBLEMS
    from wmrjax import cli

    p = cli.parser(__doc__.splitlines()[0], "results/tuning_study")
    p.add_argument("--problems", nargs="+", default=sorted(PROBLEMS), choices=sorted(PROBLEMS),
                   help="problems to run")
    p.add_argument("--seeds", type=cli.count, default=5, help="seeds per problem (scenario sets and baseline streams)")
    p.add_argument("--steps", type=cli.count, default=None, help="override every problem's optimizer steps")
    p.add_argument("--n-train", type=cli.count, default=None, help="override every problem's training scenarios")
    return p


def rows_of(problem: str, seed: int, s: dict, history: list[dict]) -> list[dict]:
    """Table rows of one run's summary and gradient history (one per method)."""
    rows = [{"problem": problem, "method": "paper_gains", "seed": seed, "heldout_loss": s["heldout_loss"]["paper_gains"],
             "best_train_loss": s["train_loss"]["paper_gains"], "rollouts_to_best": 0,
             "gradient_rollouts_to_match": None, "singularity_events": s["singularity_events"]["paper_gains"],
             "wall_time_s": 0.0},
            {"problem": problem, "method": "gradient", "seed": seed, "heldout_loss": s["heldout_loss"]["tuned"],
             "best_train_loss": min(h["train_loss"] for h in history), "rollouts_to_best": s["rollouts"],
             "gradient_rollouts_to_match": None, "singularity_events": s["singularity_events"]["tuned"],
             "wall_time_s": s["gradient_wall_time_s"]}]
    for name in ("cma_es", "random_search"):
        b = s["baselines"][name]["per_seed"][0]
        rows.append({"problem": problem, "method": name, "seed": seed, "heldout_loss": b["best_heldout_loss"],
                     "best_train_loss": b["best_loss"], "rollouts_to_best": b["rollouts_to_best"],
                     "gradient_rollouts_to_match": b["gradient_rollouts_to_match"], "singularity_events": None,
                     "wall_time_s": s["baselines"][name]["wall_time_s"]})
    return rows


def aggregate(rows: list[dict]) -> dict:
    """Per problem and method: median, min and max over seeds of every numeric column, and the
    issue's targets (held-out >= 3x below the paper's, gradient reaching CMA-ES's best with
    >= 10x fewer rollouts and ending at or below its held-out cost)."""
    import numpy as np

    out = {}
    for problem in sorted({r["problem"] for r in rows}):
        out[problem] = {}
        for method in METHODS:
            rs = [r for r in rows if r["problem"] == problem and r["method"] == method]
            if not rs:
                continue
            stats = {"seeds": len(rs)}
            for col in ("heldout_loss", "best_train_loss", "rollouts_to_best", "singularity_events", "wall_time_s"):
                v = [r[col] for r in rs if r[col] is not None]
                if v:
                    stats[col] = {"median": float(np.median(v)), "min": float(np.min(v)), "max": float(np.max(v))}
            if method in ("cma_es", "random_search"):
                m = [np.inf if r["gradient_rollouts_to_match"] is None else r["gradient_rollouts_to_match"] for r in rs]
                ratio = [r["rollouts_to_best"] / x if np.isfinite(x) else 0.0 for r, x in zip(rs, m)]
                med = float(np.median(m))
                stats["gradient_rollouts_to_match"] = {"median": med if np.isfinite(med) else None,
                                                       "matched_seeds": int(np.sum(np.isfinite(m)))}
                stats["rollout_ratio_baseline_over_gradient"] = {"median": float(np.median(ratio)),
                                                                 "min": float(np.min(ratio)), "max": float(np.max(ratio))}
            out[problem][method] = stats
        P = out[problem]
        paper, grad = P["paper_gains"]["heldout_loss"]["median"], P["gradient"]["heldout_loss"]["median"]
        checks = {"heldout_ratio_paper_over_gradient": paper / grad,
                  "heldout_3x_below_paper": paper / grad >= 3.0,
                  "no_more_singularity_events": (P["gradient"]["singularity_events"]["max"]
                                                 <= P["paper_gains"]["singularity_events"]["min"]
                                                 if "singularity_events" in P["gradient"] else None)}
        if "cma_es" in P:
            checks["rollout_ratio_vs_cma_es"] = P["cma_es"]["rollout_ratio_baseline_over_gradient"]["median"]
            checks["10x_fewer_rollouts_than_cma_es"] = checks["rollout_ratio_vs_cma_es"] >= 10.0
            checks["heldout_at_or_below_cma_es"] = grad <= P["cma_es"]["heldout_loss"]["median"]
        P["targets"] = checks
    return out


def markdown(agg: dict) -> str:
    """The aggregate as a Markdown table (median [min, max] over seeds)."""
    def f(d, key, fmt="{:.4g}"):
        if key not in d:
            return "-"
        s = d[key]
        return f"{fmt.format(s['median'])} [{fmt.format(s['min'])}, {fmt.format(s['max'])}]"

    lines = ["| problem | method | held-out loss | best train objective | rollouts to best | gradient rollouts to "
             "match | singular events (held-out) |", "|---|---|---|---|---|---|---|"]
    for problem, P in agg.items():
        for method in METHODS:
            if method not in P:
                continue
            d = P[method]
            match = d.get("gradient_rollouts_to_match")
            ms = "-" if match is None else (f"{match['median']:.0f} ({match['matched_seeds']}/{d['seeds']} seeds)"
                                            if match["median"] is not None else f"never ({match['matched_seeds']}/"
                                                                               f"{d['seeds']} seeds)")
            lines.append(f"| {problem} | {method} | {f(d, 'heldout_loss')} | {f(d, 'best_train_loss')} | "
                         f"{f(d, 'rollouts_to_best', '{:.0f}')} | {ms} | {f(d, 'singularity_events', '{:.0f}')} |")
    return "\n".join(lines)


def run(args, log=print) -> dict:
    import jax

    jax.config.update("jax_enable_x64", True)
    from tuning import cli as tuning_cli

    from tuning.problems import problem_file
    from wmrjax.problem import Problem

    out = Path(args.out)
    t0 = time.perf_counter()
    rows = []
    for name in args.problems:
        for seed in range(args.seeds):
            over = {"tune.seed": seed, "tune.baselines.seeds": 1}
            if args.steps is not None:
                over["tune.steps"] = args.steps
            if args.n_train is not None:
                over["tune.scenarios.train"] = args.n_train
            problem = Problem.load(problem_file(name)).with_values(over)
            d = out / name / f"seed_{seed}"
            done = d / "summary.json"
            s = json.loads(done.read_text()) if done.exists() else None
            if s is None or s.get("problem") != json.loads(json.dumps(problem.resolved())):
                log(f"{name}, seed {seed}: running ({time.perf_counter() - t0:.0f} s so far)")
                s = tuning_cli.run(problem, d, log=lambda msg: None)
            else:
                log(f"{name}, seed {seed}: done earlier, kept")
            history = json.loads((d / "history.json").read_text())["gradient"]
            rows += rows_of(name, seed, s, history)
    agg = aggregate(rows)
    table = markdown(agg)
    buf = _stdio.StringIO()
    wr = csv.DictWriter(buf, fieldnames=list(rows[0]))
    wr.writeheader()
    wr.writerows(rows)
    io.write_bytes(out / "study.csv", buf.getvalue().encode())
    _figure(out, rows)
    summary = {"experiment": "tuning study", "problems": list(args.problems), "seeds": args.seeds,
               "statistic": "median [min, max] over seeds", "aggregate": agg, "table_markdown": table,
               "wall_time_s": time.perf_counter() - t0}
    io.write_json(out / "summary.json", summary)
    log(table)
    return summary


def _figure(out: Path, rows: list[dict]) -> None:
    import numpy as np

    plt = io.headless_pyplot()
    problems = sorted({r["problem"] for r in rows})
    fig, axs = plt.subplots(1, len(problems), figsize=(4.2 * len(problems), 3.8), squeeze=False)
    for ax, problem in zip(axs[0], problems):
        for k, method in enumerate(METHODS):
            v = [r["heldout_loss"] for r in rows if r["problem"] == problem and r["method"] == method]
            ax.scatter(np.full(len(v), k) + np.linspace(-0.15, 0.15, len(v)), v, s=14, color=f"C{k}")
            ax.hlines(np.median(v), k - 0.3, k + 0.3, color=f"C{k}", lw=2)
        ax.set_yscale("log")
        ax.set_xticks(range(len(METHODS)), [m.replace("_", "\n") for m in METHODS], fontsize=8)
        ax.set_ylabel("held-out loss (objective)")
        ax.set_title(problem)
        ax.grid(alpha=0.3, which="both", axis="y")
    fig.suptitle("held-out loss per seed (bar: median)")
    fig.tight_layout()
    io.write_png(fig, out / "study.png")
    plt.close(fig)


def main(argv=None) -> int:
    from wmrjax import cli

    p = parser()
    a = p.parse_args(argv)
    s = cli.work(p, a, lambda progress: run(a, log=progress))
    print(f"wrote {a.out}/study.csv, summary.json, study.png ({s['wall_time_s']:.0f} s)")
    return 0


if __name__ == "__main__":
    sys.exit(main())
