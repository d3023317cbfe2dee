r"""Tracking against the certified region: a Pareto front from tuned, certified points.

    wmrjax pareto wmrjax/examples/s_path.toml --out results/s_path/pareto \
        --slice position --fractions 0 0.25 0.5 0.75 1 1.25

For every required radius (``--fractions`` times the initial gains' exact-map radius in the
slice, or ``--radii`` in output-error units) one tuning run of the problem's ``[tune]`` settings
keeps the exact-map radius at or above it throughout (:mod:`wmrjax.tune.certified`); its tuned gains
are then certified: the exact-map radius (closed form), the falsified radius (rollouts, an
upper bound found without the map) and the map's own worst initial error simulated at 0.99 and
1.01 times its size (:func:`wmrjax.tune.certified.worst_error_rollouts`). A point is *certified*
when its exact-map radius meets the requirement and rollouts confirm it to 1 %: the falsifier
within :data:`AGREEMENT` of it, or the worst error safe inside and failing outside. (The
falsifier alone can miss a brief approach to the singular set: on a 2 s test problem it
reported 31.3 m where the map's worst error of 8.80 m fails at 1.01 times its size.) Every point uses
the same scenario sets (the problem's seed), so their held-out losses compare directly: the
curve says how much tracking a user buys with how much of the safe region.

Writes ``points/*.json`` (one per requirement, atomically: a killed run resumes and keeps the
finished points), ``pareto.csv``, ``pareto.png`` and ``summary.json``.
"""

from __future__ import annotations

import csv
import dataclasses
import hashlib
import io as _stdio
import json
import time
from pathlib import Path

import jax
import jax.numpy as jnp

from wmrjax import _files as files
from wmrjax.certify import Slice
from wmrjax.problem import Problem
from wmrjax.report import JobReport
from wmrjax.tune import certified, config, loop

AGREEMENT = 0.01  # a point is certified when falsified / exact - 1 <= this
COLUMNS = (
    "required_radius",
    "fraction_of_initial",
    "tuned_radius",
    "falsified_radius",
    "falsified_over_exact",
    "worst_error_confirmed",
    "certified",
    "heldout_loss",
    "train_loss",
    "parameters",
    "steps",
    "steps_projected",
    "steps_halved",
)


POINT_FORMAT = 2  # bumped when a point's fields change: older points are computed again


def point_id(problem, slice_: str, eps: float, required: float) -> str:
    """A digest of what one point depends on (the resolved problem, the slice, eps, the radius,
    the point's format)."""
    desc = [problem.resolved(), slice_, eps, required, POINT_FORMAT]
    return hashlib.sha256(json.dumps(desc, sort_keys=True, default=str).encode()).hexdigest()[:16]


def tune_point(problem, required: float, slice_: str, eps: float, log=print) -> dict:
    """One point: tune with the requirement, then the held-out loss and the certificate of the
    tuned gains (exact map of the slice, falsified in it)."""
    setting = problem.setting("tuning")
    settings = config.read(problem.section("tune"), problem.section("certify"))
    family = settings.gain_family(setting)
    req = certified.Requirement(float(required), str(Slice(slice_)), float(eps), str(certified.Loop.NOMINAL))
    res = loop.tune(
        setting,
        family,
        settings.optimizer.build(settings.steps),
        steps=settings.steps,
        scenarios=settings.scenarios,
        loss=settings.loss,
        stopping=settings.stopping,
        seed=settings.seed,
        log=lambda msg: None,
        requirement=req,
    )
    raw = jnp.asarray(res.best_raw)
    ctx = res.context
    val, ok, _ = loop.mean_loss(raw, ctx.sets.heldout, setting, family, ctx.weights)
    tr, tr_ok, _ = loop.mean_loss(raw, ctx.sets.train, setting, family, ctx.weights)
    log(f"required {required:.4g}: tuned {list(map(float, family.positive(raw)))}; certifying (exact map, falsifier)")
    rad = certified.radii(setting, family.gains(raw), eps=eps, falsify=slice_, seed=settings.seed)
    block = rad[f"exact_map_{slice_}"]
    held = block["radius"]  # the attained radius, the one the tuner keeps (differentiable)
    agree = block["falsified_over_exact"]
    confirmed = block["worst_error_rollouts"]["confirmed"]
    return {
        "required_radius": float(required),
        "tuned_radius": held,
        "falsified_radius": block["falsified"],
        "falsified_over_exact": agree,
        "worst_error_confirmed": confirmed,
        "certified": bool(held >= required and (confirmed or (agree is not None and agree - 1.0 <= AGREEMENT))),
        "heldout_loss": float(loop.objective(val, ok)),
        "train_loss": float(loop.objective(tr, tr_ok)),
        "parameters": dict(zip(family.names(), map(float, family.positive(raw))))
        if family.size <= 12
        else [float(v) for v in family.positive(raw).reshape(-1)],
        "steps": len(res.history),
        "steps_projected": sum(h.get("halvings") == -1 for h in res.history),
        "steps_halved": sum(h.get("halvings", 0) > 0 for h in res.history),
        "radii": rad,
    }


@dataclasses.dataclass(frozen=True)
class ParetoReport(JobReport):
    """The Pareto front of tracking against the certified region (:func:`run`).

    Attributes:
        problem: the problem tuned.
        slice: the slice whose exact-map radius was required (:class:`wmrjax.certify.Slice`).
        eps: the margin to the singular set [output-error units].
        initial: the initial gains' radius and held-out and training losses.
        points: per required radius (ascending), the tuned point: ``required_radius``,
            ``tuned_radius``, ``falsified_radius``, ``certified``, the losses, the parameters
            (the columns of ``pareto.csv``, :data:`COLUMNS`).
        wall_time_s: the job's wall time [s].
    """

    problem: Problem
    slice: Slice
    eps: float
    initial: dict
    points: tuple
    wall_time_s: float

    @property
    def every_point_certified(self) -> bool:
        """Whether every point's tuned radius is at least its requirement and the falsifier agrees."""
        return all(p["certified"] for p in self.points)

    def summary(self) -> dict:
        """``summary.json`` (plain JSON)."""
        return files.jsonable(
            {
                "experiment": "pareto",
                "problem_name": self.problem.title,
                "problem": self.problem.resolved(),
                "slice": self.slice,
                "eps": self.eps,
                "agreement_tolerance": AGREEMENT,
                "initial_gains": self.initial,
                "points": [{k: p[k] for k in COLUMNS} for p in self.points],
                "every_point_certified": self.every_point_certified,
                "note": "tuned_radius: the exact-map radius of the tuned gains (closed form); falsified_radius: the "
                "smallest initial error the falsifier drives within eps (rollouts, an upper bound)",
                "wall_time_s": self.wall_time_s,
            }
        )


def run(problem, out: Path, slice_: str = Slice.FULL, fractions=None, radii=None, eps=None, log=print) -> ParetoReport:
    """Every point (resuming finished ones), then the table, the figure and ``summary.json``.

    Args:
        problem: the problem (:class:`wmrjax.problem.Problem`) with a certifiable closed loop.
        out: the output directory (``Path``): ``points/`` holds each finished point (resumed).
        slice_: the slice whose exact-map radius is required (:class:`wmrjax.certify.Slice`).
        fractions: the required radii as multiples of the initial gains' (default: 0 to 1.25).
        radii: the required radii [output-error units] (instead of ``fractions``).
        eps: the margin to the singular set (default: the problem's ``[certify] eps``).
        log: called with each progress message.

    Returns:
        the :class:`ParetoReport`.
    """
    jax.config.update("jax_enable_x64", True)

    t0 = time.perf_counter()
    setting = problem.setting("tuning")
    settings = config.read(problem.section("tune"), problem.section("certify"))
    family = settings.gain_family(setting)
    eps = float(eps if eps is not None else problem.section("certify").get("eps", certified.DEFAULT_EPS))
    raw0 = loop.initial_raw(setting, family)
    initial = certified.radius_function(
        setting, family, certified.Requirement(0.0, str(Slice(slice_)), eps, str(certified.Loop.NOMINAL))
    ).value(jnp.asarray(raw0))
    if radii is None:
        fractions = fractions if fractions is not None else (0.0, 0.25, 0.5, 0.75, 1.0, 1.25)
        radii = [f * initial for f in fractions]
    points = []
    for i, required in enumerate(sorted(radii)):
        path = out / "points" / f"point_{i:02d}.json"
        pid = point_id(problem, slice_, eps, required)
        old = json.loads(path.read_text()) if path.exists() else None
        if old is not None and old.get("id") == pid:
            log(f"point {i + 1}/{len(radii)} (required {required:.4g}): done earlier, kept")
            points.append(old)
            continue
        log(
            f"point {i + 1}/{len(radii)}: tuning with the exact-map radius ({slice_}) >= {required:.4g} "
            f"({time.perf_counter() - t0:.0f} s so far)"
        )
        pt = {"id": pid, **tune_point(problem, required, slice_, eps, log), "fraction_of_initial": required / initial}
        files.write_json(path, pt)
        points.append(pt)
    return _write(out, problem, setting, family, raw0, slice_, eps, initial, points, time.perf_counter() - t0)


def _initial_point(setting, family, settings, raw0) -> dict:
    """The initial gains' held-out and training losses on the points' scenario sets."""
    ctx = loop.prepare(setting, family, settings.scenarios, settings.loss, settings.seed)
    raw = jnp.asarray(raw0)
    val, ok, _ = loop.mean_loss(raw, ctx.sets.heldout, setting, family, ctx.weights)
    tr, tr_ok, _ = loop.mean_loss(raw, ctx.sets.train, setting, family, ctx.weights)
    return {"heldout_loss": float(loop.objective(val, ok)), "train_loss": float(loop.objective(tr, tr_ok))}


def _write(out, problem, setting, family, raw0, slice_, eps, initial, points, wall) -> ParetoReport:
    """``pareto.csv``, ``pareto.png`` and ``summary.json`` of the finished points."""
    settings = config.read(problem.section("tune"), problem.section("certify"))
    base = {"radius": initial, **_initial_point(setting, family, settings, raw0)}
    buf = _stdio.StringIO()
    wr = csv.DictWriter(buf, fieldnames=list(COLUMNS))
    wr.writeheader()
    for p in points:
        wr.writerow({k: json.dumps(p[k]) if isinstance(p[k], (dict, list)) else p[k] for k in COLUMNS})
    files.write_bytes(out / "pareto.csv", buf.getvalue().encode())
    _figure(out, problem.title, slice_, eps, base, points)
    report = ParetoReport(problem, Slice(slice_), eps, base, tuple(points), wall)
    report.write_summary(out)
    return report


def _figure(out, title, slice_, eps, base, points) -> None:
    plt = files.headless_pyplot()
    fig, ax = plt.subplots(figsize=(6.8, 4.4))
    req = [p["required_radius"] for p in points]
    got = [p["tuned_radius"] for p in points]
    loss = [p["heldout_loss"] for p in points]
    ax.plot(got, loss, "C0o-", label="tuned with the requirement (at its certified radius)")
    for r, g, l_, p in zip(req, got, loss, points):
        ax.plot([r, g], [l_, l_], "C0:", lw=0.8)
        if not p["certified"]:
            ax.plot(g, l_, "rx", ms=9, label="not certified (falsifier disagrees)")
    ax.plot(req, loss, "C0|", ms=10, label="required radius")
    ax.plot([base["radius"]], [base["heldout_loss"]], "C3*", ms=12, label="initial gains")
    ax.set_yscale("log")
    ax.set_xlabel(f"certified exact-map radius, {slice_} slice [m{', m/s' if slice_ == Slice.FULL else ''}]")
    ax.set_ylabel("held-out loss (objective)")
    ax.set_title(f"{title}: tracking vs certified region (eps = {eps:g})", fontsize=10)
    ax.grid(alpha=0.3, which="both")
    handles, labels = ax.get_legend_handles_labels()
    keep = dict(zip(labels, handles))
    ax.legend(keep.values(), keep.keys(), fontsize=7)
    fig.tight_layout()
    files.write_png(fig, out / "pareto.png")
    plt.close(fig)
